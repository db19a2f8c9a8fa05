"""Emit Algorithm 4.1 (thesis Chapter 4, SPEC §2.21) with (4.5) solved hot in C: the C
form of the default :class:`~balustrade.control.rapsf.RAPSF` (docs/deploy_c.md, "Session
15"), one call ``<name>_step(x, u_p, theta, s, falsified, u_out, status, work)`` per step
(``bal/rapsf_hot.h``, the interface of ``bal/rapsf.h``).

The QP is the direct backend's lowered (4.5) — ``q = q0 + Q p``, ``b = b0 + B p`` and the
values of ``A(p)`` affine in the parameters ``p = (x0, u_p, θ vertices, s_jr)`` — written
as data (sparse matrices) into ``<name>_config.h``; the C evaluates them, solves the QP with
the dense active-set library of the casadi wheel kept across steps (hot start from the last
working set) and accepts an answer only with the solver's optimal flag *and* the scaled KKT
residual of the Python engine below its tolerance (computed in C); an unverified answer is
solved again cold, then the stored plan / backup ``K x`` apply. Python's engine asks its
sparse interior-point fallback instead: C and Python differ only on such steps.

What this path does not emit (:class:`~balustrade.errors.CodegenError` naming the
alternative, the target ``"convex-qp"`` of :mod:`~balustrade.codegen.emit_rapsf`): Remark
4.6 (``shrinking``), a backup other than ``K x``, ``warm_start`` (the hot start replaces it).
"""

from __future__ import annotations

import json
from pathlib import Path

import casadi as ca
import numpy as np
import scipy.sparse as sp

from balustrade.backends import lowered_for_c
from balustrade.codegen import cfiles as C
from balustrade.codegen import status as S
from balustrade.codegen.emit import MANIFEST_VERSION, Emitted
from balustrade.control.deploy import RAPSFDeployment
from balustrade.errors import CodegenError, SolverError

#: the static C of this step (copied into ``bal/`` with the others)
STATIC = ("rapsf_hot.h", "rapsf_hot.c")


def lowered(spec: RAPSFDeployment, name: str) -> dict | None:
    """The lowered (4.5) of ``spec`` when it was compiled for the hot-started engine (the
    default target on small problems), else ``None``."""
    try:
        low = lowered_for_c(spec.problems["main"])
    except SolverError as exc:
        raise CodegenError(f"{name}: {exc}") from exc
    if low is None and getattr(spec.host, "shared_rows_problem", None) is not None:
        found = spec.host.shared_rows_problem()
        if found is not None and lowered_for_c(found[0]) is not None:
            m, n = spec.problems["main"].program.A.shape if hasattr(
                spec.problems["main"], "program") else ("?", "?")
            raise CodegenError(
                f"{name}: the Python step solves (4.5) with shared rows on the hot-started "
                f"engine, but (4.5) with every row ({m} x {n}, needed in C for vertex data "
                "that do not repeat those rows) is above that engine's size limit; build "
                "the RAPSF with target='convex-qp'")
    return low


def _ints(cfg: C.Config, name: str, values: np.ndarray) -> None:
    vals = [str(int(v)) for v in np.asarray(values).reshape(-1)] or ["0"]
    cfg.define(name, "{" + ", ".join(vals) + "}")


def _csr(cfg: C.Config, name: str, tag: str, S_: sp.csr_matrix) -> None:
    S_ = sp.csr_matrix(S_)
    S_.sort_indices()
    _ints(cfg, f"{name}_{tag}_PTR", S_.indptr)
    _ints(cfg, f"{name}_{tag}_COL", S_.indices)
    cfg.array(f"{name}_{tag}_VAL", S_.data)


def emit_hot(spec: RAPSFDeployment, name: str, out_dir: Path, low: dict) -> Emitted:
    """Write the module (``out_dir`` exists, ``name`` checked) of the hot-started step."""
    if spec.shrinking:
        raise CodegenError(f"{name}: shrinking=True (Remark 4.6) is not emitted with the "
                           "hot-started QP; build the RAPSF with target='convex-qp'")
    if not spec.default_backup:
        raise CodegenError(f"{name}: a backup other than K x is not emitted with the "
                           "hot-started QP; build the RAPSF with target='convex-qp'")
    if getattr(spec.host, "warm_start", False):
        raise CodegenError(f"{name}: warm_start=True is a start of the SQP of target "
                           "'convex-qp'; the hot-started QP starts from its last working set")
    compiled = spec.problems["main"]
    ocp = compiled.ocp
    entries = {e.name: e for e in ocp.parameter_layout.entries}
    missing = [k for k in ("x0", "u_p", "theta", "s") if k not in entries]
    if missing or "v" not in ocp.variable_layout.by_name:
        raise CodegenError(f"{name}: (4.5) needs the parameters x0, u_p, theta, s and the "
                           f"variable v (missing {missing}); build it with rapsf_problem")
    K = np.asarray(spec.K, dtype=float)
    nu, nx = K.shape
    nq, nth = (list(entries["theta"].shape) + [1])[:2]
    nxr = int(entries["s"].shape[0])
    n_w = low["n_w"]
    vidx = _vidx(compiled, n_w)
    if vidx.shape != (nu, spec.N) or entries["x0"].shape[0] != nx or nth != spec.n_vertices:
        raise CodegenError(f"{name}: (4.5) has v {vidx.shape}, x0 {entries['x0'].shape}, "
                           f"theta {entries['theta'].shape}; expected ({nu}, {spec.N}), "
                           f"({nx},), (q, {spec.n_vertices})")
    p_init = ocp.pack_parameters({k: np.zeros(entries[k].shape) for k in
                                  ("x0", "u_p", "theta", "s")})
    if np.any(p_init != 0):
        raise CodegenError(f"{name}: (4.5) has parameters beyond x0, u_p, theta, s")
    qps = {"ALL": (low, vidx)}
    shared = _shared(spec, name, entries, low)
    if shared is not None:
        qps["SH"] = shared[0]
    opts = low["options"]
    cfg = C.Config()
    cfg.comment(f"---- Algorithm 4.1, the RAPSF step {name} with (4.5) hot-started "
                "(bal/rapsf_hot.h) ----")
    for key, val, doc in (("NX", nx, None), ("NU", nu, None), ("N", spec.N, None),
                          ("NQ", nq, "parameters θ"),
                          ("NTH", nth, "vertex columns of theta and s"),
                          ("NXR", nxr, "rows of H_X (rows of s)"),
                          ("NP", p_init.size, "entries of the parameter vector p"),
                          ("SHARED", int(shared is not None),
                           "1: also (4.5) with the shared rows (SH), used when the data "
                           "repeat them")):
        cfg.define(f"{name}_{key}", val, doc)
    for key in ("x0", "u_p", "theta", "s"):
        cfg.define(f"{name}_P_{key}", entries[key].slice.start, f"offset of {key} in p")
    cfg.array(f"{name}_K", K.T.reshape(-1), nu * nx)
    cfg.define(f"{name}_PRIMAL_TOL", C.c_double(opts["primal_tol"]))
    cfg.define(f"{name}_PROX", C.c_double(opts["prox"]),
               "semi-proximal weight on the zero diagonal entries of P")
    cfg.define(f"{name}_PROX_ITER", int(opts["prox_iter"]), "proximal iterations at most")
    cfg.define(f"{name}_KKT_TOL", C.c_double(low["kkt_tol"]))
    if shared is not None:
        _, rep, dep = shared
        _ints(cfg, f"{name}_REP", rep.T.reshape(-1))
        _ints(cfg, f"{name}_DEP", dep.T.reshape(-1))
    for tag, (lw, vi) in qps.items():
        _qp_config(cfg, name, tag, lw, vi, opts["prox"])
    cfg.status(S.RAPSF, "BAL_RAPSF_STATUS_CODES")
    sizes = {("all" if tag == "ALL" else "shared"): list(lw["A"].shape[:1]) + [lw["P"].shape[0]]
             for tag, (lw, _) in qps.items()}
    return _write(spec, name, out_dir, cfg, low["library"],
                  {"kind": "rapsf", "qp": "hot", "nx": nx, "nu": nu, "N": spec.N, "nq": nq,
                   "n_vertices": nth, "n_rows": nxr, "shrinking": False,
                   "warm_start": False, "K": K.tolist(), "backup": "default",
                   "qp_size": sizes["all"], "qp_sizes": sizes,
                   "options": {**opts, "kkt_tol": low["kkt_tol"]},
                   "problems": {}, "rapsf_status": S.manifest(S.RAPSF)})


def _vidx(compiled: object, n_w: int) -> np.ndarray:
    """The indices of ``v`` (``nu × N``) in the lowered QP's variables."""
    return np.asarray(compiled.ocp.unpack_variables(np.arange(n_w, dtype=float))["v"],
                      dtype=float)


def _shared(spec: RAPSFDeployment, name: str, entries: dict, low: dict
            ) -> tuple[tuple[dict, np.ndarray], np.ndarray, np.ndarray] | None:
    """(4.5) with the shared rows (the QP the Python step solves when the vertex data repeat
    them), lowered for C with its ``rep`` and ``dependence``; ``None`` when the host shares
    no row or that QP is not on the hot-started engine."""
    get = getattr(spec.host, "shared_rows_problem", None)
    found = get() if get is not None else None
    if found is None:
        return None
    compiled, rep, dep = found
    low_sh = lowered_for_c(compiled)
    if low_sh is None:
        return None
    layout = {e.name: (e.slice.start, e.shape) for e in compiled.ocp.parameter_layout.entries}
    if layout != {k: (e.slice.start, e.shape) for k, e in entries.items()} or \
            rep.shape != entries["s"].shape or dep.shape != (entries["s"].shape[0],
                                                             entries["theta"].shape[0]):
        raise CodegenError(f"{name}: (4.5) with shared rows has another parameter layout "
                           "than (4.5) with every row")
    return (low_sh, _vidx(compiled, low_sh["n_w"])), rep, dep


def n_p_of(low: dict) -> int:
    """Entries of the parameter vector of a lowered QP."""
    return int(low["Q"].shape[1])


def _cost_constant(low: dict, n_p: int) -> tuple[sp.csr_matrix, np.ndarray, float]:
    """The part of (4.5)'s cost that depends on ``p`` only, ``½pᵀCp + gᵀp + c0`` (e.g.
    ``‖u_p‖²`` terms of ``‖v_0 − u_p‖²``): Python's reported objective is the cost itself,
    the QP's value ``½yᵀPy + qᵀy`` lacks it. Read from the cost function at ``y = 0`` by
    CasADi's derivatives and checked at random points, with ``y`` too (the whole cost equals
    QP value + constant); a cost of another form → :class:`CodegenError`."""
    f = low["objective"]
    p = ca.SX.sym("p", n_p)
    c = f(ca.DM.zeros(low["n_w"]), p)
    hess, grad = ca.hessian(c, p)
    fn = ca.Function("c", [p], [hess, grad, c])
    Hm, gm, c0 = (np.asarray(ca.DM(v).full()) for v in fn(np.zeros(n_p)))
    Cq, g, c0 = sp.csr_matrix(Hm), gm.reshape(-1), float(c0.reshape(-1)[0])
    rng = np.random.default_rng(0)
    P = sp.csc_matrix(low["P"])
    for _ in range(3):
        pv, y = rng.normal(size=n_p), rng.normal(size=P.shape[0])
        q = low["q0"] + low["Q"] @ pv
        model = 0.5 * y @ (P @ y) + q @ y + 0.5 * pv @ (Cq @ pv) + g @ pv + c0
        true = float(np.asarray(f(y[:low["n_w"]], pv)).reshape(-1)[0])
        if not abs(model - true) <= 1e-9 * (1.0 + abs(true)):
            raise CodegenError("the cost of (4.5) is not ½yᵀPy + q(p)ᵀy + a quadratic in p "
                               f"(checked: {model!r} vs {true!r}); build the RAPSF with "
                               "target='convex-qp'")
    return Cq, g, c0


def _qp_config(cfg: C.Config, name: str, tag: str, low: dict, vidx: np.ndarray,
               prox: float) -> None:
    """The arrays ``<name>_<tag>_*`` of one lowered QP (bal/rapsf_hot.c); its cost with the
    proximal term must be positive definite."""
    n, m = low["P"].shape[0], low["A"].shape[0]
    cfg.comment(f"the lowered (4.5) {tag}: {m} rows, {n} variables")
    cfg.define(f"{name}_{tag}_NY", n)
    cfg.define(f"{name}_{tag}_M", m)
    cfg.define(f"{name}_{tag}_M0", low["m0"])
    cfg.define(f"{name}_{tag}_NNZ", low["A"].nnz)
    P = sp.csc_matrix(low["P"])
    P.sort_indices()
    dense = P.toarray()
    dense[np.diag_indices(n)] += np.where(np.diag(dense) == 0, prox, 0.0)
    try:
        np.linalg.cholesky(dense)
    except np.linalg.LinAlgError:
        raise CodegenError(f"{name}: the cost of (4.5) with the proximal term on its zero "
                           "diagonal entries is not positive definite; build the RAPSF with "
                           "target='convex-qp'") from None
    _ints(cfg, f"{name}_{tag}_P_COLPTR", P.indptr)
    _ints(cfg, f"{name}_{tag}_P_ROW", P.indices)
    cfg.array(f"{name}_{tag}_P_VAL", P.data)
    cfg.array(f"{name}_{tag}_Q0", low["q0"], n)
    _csr(cfg, f"{name}_{tag}", "QQ", low["Q"])
    cfg.array(f"{name}_{tag}_B0", low["b0"], m)
    _csr(cfg, f"{name}_{tag}", "BB", low["B"])
    Cq, g, c0 = _cost_constant(low, n_p_of(low))
    cfg.comment("the cost's part in p alone, 1/2 p'Cp + g'p + c0 (objective = QP value + it)")
    _csr(cfg, f"{name}_{tag}", "OC", Cq)
    cfg.array(f"{name}_{tag}_OG", g)
    cfg.define(f"{name}_{tag}_O0", C.c_double(c0))
    A = low["A"]
    _ints(cfg, f"{name}_{tag}_A_COLPTR", A.indptr)
    _ints(cfg, f"{name}_{tag}_A_ROW", A.indices)
    cfg.array(f"{name}_{tag}_A0", A.data)
    _csr(cfg, f"{name}_{tag}", "AP", low["A_param"])
    _ints(cfg, f"{name}_{tag}_VIDX", vidx.T.reshape(-1))


def _write(spec: RAPSFDeployment, name: str, out_dir: Path, cfg: C.Config, lib: str,
           manifest: dict) -> Emitted:
    from balustrade.codegen.emit_rapsf import link_flags

    static = C.copy_static(out_dir)
    what = "Algorithm 4.1, the RAPSF (4.5), hot-started"
    cfg_path = out_dir / f"{name}_config.h"
    h, c = out_dir / f"{name}.h", out_dir / f"{name}.c"
    cfg_path.write_text(C.config_header(name, what, cfg))
    guard = f"{name.upper()}_H"
    h.write_text("\n".join([
        f"/* {name}.h: the C entry points of {what}, generated by balustrade.",
        f" * Compile {name}.c (bal/ next to it) with the link flags of {name}.json",
        " * (the solver library of the casadi wheel). Entry points: bal/rapsf_hot.h with",
        f" * the prefix {name} ({name}_init, _finalize, _alloc, _free, _reset, _step, ...). */",
        f"#ifndef {guard}", f"#define {guard}", "",
        "#ifndef casadi_real", "#define casadi_real double", "#endif",
        "#ifndef casadi_int", "#define casadi_int long long int", "#endif",
        f'#include "{name}_config.h"', f'#include "{C.SUBDIR}/common.h"', "",
        "#ifdef __cplusplus", 'extern "C" {', "#endif",
        f"#define BAL_STEP {name}", f'#include "{C.SUBDIR}/rapsf_hot.h"', "#undef BAL_STEP",
        "#ifdef __cplusplus", '} /* extern "C" */', "#endif", "", f"#endif /* {guard} */", ""]))
    c.write_text("\n".join([f"/* {name}.c: bal/rapsf_hot.c instantiated for {name}. */",
                            f'#include "{name}.h"', f"#define BAL_STEP {name}",
                            f'#include "{C.SUBDIR}/rapsf_hot.c"', "#undef BAL_STEP", ""]))
    manifest = {"version": MANIFEST_VERSION, "name": name, "casadi": ca.__version__,
                "libraries": [lib], **manifest, "link_flags": list(link_flags((lib,))),
                "status_codes": S.manifest(S.SOLVE)}
    (out_dir / f"{name}.json").write_text(json.dumps(manifest, indent=1))
    return Emitted(name, out_dir, [c], [h, cfg_path], manifest, (lib,), static)


__all__ = ["STATIC", "emit_hot", "lowered"]
