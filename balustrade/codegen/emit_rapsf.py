"""Emit Algorithm 4.1, the robust adaptive predictive safety filter (thesis Chapter 4, SPEC
§2.21), as one C call per control step.

:func:`emit_rapsf` writes the module of :mod:`~balustrade.codegen.emit` (``bal/``,
``<name>_config.h``, ``<name>.h/.c``, ``<name>_casadi.c/.h``, ``<name>.json``) with the step
``<name>_step(x, u_p, theta, s, falsified, u_out, status, work)`` of ``bal/rapsf.c``: the QP
(4.5) with the vertices of ``Θ_k`` and the constants ``s_jr`` (SPEC §2.20) as parameters,
``u = K x + v*_0`` after a converged solve (the plan stored, ``k_inf = 0``), else the stored
plan ``K x + v*_{k_inf}`` while ``k_inf <= N − 1``, else the backup ``K x``.

The Remark 4.6 shrinking variant (``shrinking=True``) is emitted too: (4.5) with every
shorter horizon ``h = 1 … N−1`` is one more problem ``<name>_shrunk<h>`` of the module (same
parameters ``x0, u_p, theta, s``), and after a failed (4.5) with ``k_inf <= N − 1`` and a
stored plan the step first solves the one with ``h = N − k_inf`` and applies its
``K x + v*_0`` (``BAL_RAPSF_SHRUNK_HORIZON``; its ``v̂`` becomes the stored plan from stage
``k_inf`` on and ``k_inf`` keeps counting, as in :class:`~balustrade.control.rapsf.RAPSF`),
falling back to the stored plan if it fails too.

What stays in the host language: the set-membership estimator (line 4 of Algorithm 4.1, LPs
or the box update of :mod:`balustrade.estimate`) with the nesting check of Assumption 4.2,
and ``s_jr`` of the new vertices (:func:`~balustrade.problems.rapsf.s_constants`); they
change the QP's parameters only, never its structure. :class:`~balustrade.codegen.CRAPSF`
runs them in Python (on a copy of the controller) and passes the data to the C step.

The backup policy ``π_Cf`` (:mod:`balustrade.control.rapsf_backup`) is the default ``K x``, an
affine law ``K_b x + k_b`` (``<name>_KB``, ``<name>_KB0`` in the config header) or a
``casadi.Function`` of ``x`` emitted as ``<name>_backup_policy`` (expanded to scalar
operations), selected by ``<name>_BACKUP`` (0, 1, 2); the C applies it where
:class:`~balustrade.control.rapsf.RAPSF` does (``k_inf > N − 1``, a falsified model, a
non-finite state with its NaN entries read as 0).

A RAPSF on the default target whose (4.5) was compiled for the hot-started dense engine
(small problems, e.g. 3 masses) is emitted by :mod:`~balustrade.codegen.emit_rapsf_hot`
instead: (4.5) hot-started in C (``bal/rapsf_hot.c``, docs/deploy_c.md "Session 15").

Not emitted (:class:`~balustrade.errors.CodegenError`): a Python callable as backup, the
terminal-set enlargement. Otherwise the controller must be built on a CasADi target that
can be emitted; the QP (4.5) needs :data:`EMITTABLE_TARGET` (``"convex-qp"``, a dual active-set QP
solver inside the SQP; the self-contained ``"fast-sqp"`` cycles on this QP's degenerate
active sets and fails, docs/deploy_c.md). Its C links that solver's library, shipped with
the casadi wheel (``Emitted.libraries``): :func:`link_flags` gives the flags for
:func:`~balustrade.codegen.build.build`.
"""

from __future__ import annotations

from pathlib import Path

import casadi as ca
import numpy as np

from balustrade.codegen import cfiles as C
from balustrade.codegen import status as S
from balustrade.codegen.emit import (
    Emitted,
    _check_accept_tol,
    _check_compiled,
    _check_identifier,
    _generate,
    _out_dir,
    _Problem,
    _require,
    _spec,
    _write_module,
)
from balustrade.codegen.emit_rapsf_hot import emit_hot, lowered
from balustrade.codegen.support import check_no_callbacks
from balustrade.control.deploy import RAPSFDeployment
from balustrade.control.rapsf_backup import AffineBackup, FunctionBackup
from balustrade.errors import BalustradeError, CodegenError

#: the target to build :class:`~balustrade.control.rapsf.RAPSF` with for C
EMITTABLE_TARGET = "convex-qp"


def casadi_dir() -> Path:
    """The installed casadi package folder: the solver libraries it ships and, in
    ``include/``, their headers."""
    return Path(ca.__file__).resolve().parent


def link_flags(libraries: tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """Compiler flags for C that links the solver ``libraries`` shipped in the casadi wheel
    (``-I``/``-L`` its folders, ``-l<lib>`` forced in with ``--no-as-needed``: the build
    lists them before the sources, and an rpath so the library loads)."""
    if not libraries:
        return ()
    root = casadi_dir()
    return (f"-I{root / 'include'}", f"-L{root}", f"-Wl,-rpath,{root}", "-Wl,--no-as-needed",
            *(f"-l{lib}" for lib in libraries))


def emit_rapsf(controller: object, name: str, out_dir: str | Path,
               allow_external: bool = True, accept_tol: float | None = None) -> Emitted:
    """Emit Algorithm 4.1 of a :class:`~balustrade.control.rapsf.RAPSF` as one C call per
    control step. A RAPSF on the default target whose (4.5) got the hot-started dense
    engine (small problems, e.g. 3 masses) is emitted with that QP hot-started in C
    (:mod:`~balustrade.codegen.emit_rapsf_hot`, ``bal/rapsf_hot.h``); one built with
    ``target="convex-qp"`` (:data:`EMITTABLE_TARGET`) as the SQP of that target (module
    docstring; ``bal/rapsf.h``). ``allow_external`` (default True) admits a QP solver whose
    C links a library (:func:`link_flags`)."""
    _check_identifier(name)
    _check_accept_tol(name, accept_tol)
    spec = _spec(controller, name, RAPSFDeployment, "RAPSF")
    if getattr(spec.host, "enlargement", None) is not None:
        raise CodegenError(f"{name}: the terminal-set enlargement (enlarge=True) records its "
                           "generators in Python and is not emitted; build the RAPSF without "
                           "enlarge")
    low = lowered(spec, name)
    if low is not None:     # the default target on small (4.5): the hot-started QP in C
        return emit_hot(spec, name, _out_dir(out_dir, name), low)
    backup = _backup_law(spec, name)
    compiled = spec.problems["main"]
    try:
        libs = _check_compiled(compiled, f"{name}: the QP (4.5)", allow_external)
    except CodegenError as exc:
        raise CodegenError(f"{exc}; for Algorithm 4.1 build the RAPSF with "
                           f"target={EMITTABLE_TARGET!r}") from exc
    out_dir = _out_dir(out_dir, name)
    P = _Problem(compiled, f"{name}_main", f"the RAPSF QP (4.5) {compiled.ocp.name!r}", name,
                 accept_tol)
    _require(name, {"(4.5) parameter": (P.params, ["x0", "u_p", "theta", "s"]),
                    "(4.5) variable": (P.vars, ["v"])},
             "build (4.5) with balustrade.problems.rapsf.rapsf_problem (n_vertices=...)")
    K = np.asarray(spec.K, dtype=float)
    nu, nx = K.shape
    nq, nth = (list(P.params["theta"]["shape"]) + [1])[:2]
    nxr = int(P.params["s"]["shape"][0])
    if list(P.vars["v"]["shape"]) != [nu, spec.N] or int(P.params["x0"]["shape"][0]) != nx \
            or nth != spec.n_vertices:
        raise CodegenError(f"{name}: (4.5) has v {P.vars['v']['shape']}, x0 "
                           f"{P.params['x0']['shape']}, theta {P.params['theta']['shape']}; "
                           f"expected ({nu}, {spec.N}), ({nx},), (q, {spec.n_vertices})")
    shrunk, libs = _shrunk_problems(spec, name, P, nu, accept_tol, allow_external, libs)
    functions = P.functions()
    for Ph in shrunk.values():
        functions.update(Ph.functions())
    if isinstance(backup, FunctionBackup):
        functions[f"{name}_backup_policy"] = backup.emittable(name)
    files = _generate(functions, name, out_dir)
    cfg = C.Config()
    P.config(cfg)
    for Ph in shrunk.values():
        Ph.config(cfg)
    cfg.comment(f"---- Algorithm 4.1, the RAPSF step {name} (bal/rapsf.h) ----")
    cfg.define(f"{name}_NX", nx)
    cfg.define(f"{name}_NU", nu)
    cfg.define(f"{name}_N", spec.N)
    cfg.define(f"{name}_NQ", nq, "parameters θ")
    cfg.define(f"{name}_NTH", nth, "vertex columns of theta and s")
    cfg.define(f"{name}_NXR", nxr, "rows of H_X (rows of s)")
    cfg.array(f"{name}_K", K.T.reshape(-1), nu * nx)
    warm = bool(getattr(spec.host, "warm_start", False))
    cfg.define(f"{name}_WARM_START", int(warm),
               "(4.5) from the previous step's solution after a converged solve")
    cfg.define(f"{name}_SHRINKING", int(bool(shrunk)),
               "Remark 4.6: (4.5) with the horizon N - k_inf before the stored plan")
    cfg.comment("the problems (4.5) with the shrunk horizons: X(member of the work struct, h)")
    cfg.xmacro(f"{name}_SHRUNK", [f"{key}, {key.removeprefix('shrunk')}" for key in shrunk])
    backup_kind = _backup_config(cfg, name, backup, nu, nx)
    cfg.status(S.RAPSF, "BAL_RAPSF_STATUS_CODES")
    manifest = {"kind": "rapsf", "nx": nx, "nu": nu, "N": spec.N, "nq": nq,
                "n_vertices": nth, "n_rows": nxr, "shrinking": bool(shrunk),
                "warm_start": warm, "K": K.tolist(), "backup": backup_kind,
                "link_flags": list(link_flags(libs)),
                "problems": {"main": P.manifest(),
                             **{key: Ph.manifest() for key, Ph in shrunk.items()}},
                "rapsf_status": S.manifest(S.RAPSF)}
    parts = [("problem", P.P), *[("problem", Ph.P) for Ph in shrunk.values()],
             ("rapsf", name)]
    return _write_module(name, out_dir, "Algorithm 4.1, the RAPSF (4.5)", cfg, parts, files,
                         manifest, tuple(sorted(set(libs))))


def _backup_law(spec: RAPSFDeployment, name: str) -> AffineBackup | FunctionBackup | None:
    """The emittable backup law of the controller (``None``: the default ``K x``); a Python
    callable → :class:`CodegenError` naming ``backup`` (nothing written yet)."""
    if spec.default_backup:
        return None
    law = getattr(spec.host, "backup_law", None)
    if not isinstance(law, (AffineBackup, FunctionBackup)):
        raise CodegenError(f"{name}: backup is a Python callable "
                           f"({type(getattr(spec.host, 'backup', None)).__name__}); its body "
                           "cannot be emitted as C. Give the RAPSF backup=(K_b, k_b) (the "
                           "affine law K_b x + k_b) or backup=<casadi.Function of x>, or no "
                           "backup (K x)")
    if isinstance(law, FunctionBackup):
        check_no_callbacks(law.fn, f"{name}: backup (casadi.Function {law.fn.name()!r})")
        try:
            law.emittable(name)
        except BalustradeError as exc:
            raise CodegenError(str(exc)) from exc
    return law


def _backup_config(cfg: C.Config, name: str, law: AffineBackup | FunctionBackup | None,
                   nu: int, nx: int) -> str:
    """``<name>_BACKUP`` (0: ``K x``, 1: ``K_b x + k_b``, 2: ``<name>_backup_policy(x)``)
    and the affine law's data; returns the manifest word."""
    kind = 0 if law is None else 1 if isinstance(law, AffineBackup) else 2
    cfg.define(f"{name}_BACKUP", kind, "the backup policy: 0 K x, 1 K_b x + k_b, 2 the "
               f"emitted function {name}_backup_policy(x)")
    if isinstance(law, AffineBackup):
        cfg.array(f"{name}_KB", law.K_b.T.reshape(-1), nu * nx)
        cfg.array(f"{name}_KB0", law.k_b, nu)
    return ("default", "affine", "function")[kind]


def _shrunk_problems(spec: RAPSFDeployment, name: str, P: _Problem, nu: int,
                     accept_tol: float | None, allow_external: bool,
                     libs: tuple[str, ...]) -> tuple[dict[str, _Problem], tuple[str, ...]]:
    """The problems (4.5) with the horizons ``h = 1 … N−1`` of Remark 4.6 (``{}`` without
    ``shrinking``), each checked for C and for the parameter layout of the main problem
    (the step passes one parameter vector to all of them)."""
    if not spec.shrinking:
        return {}, libs
    out: dict[str, _Problem] = {}
    for h in range(1, spec.N):
        key = f"shrunk{h}"
        compiled = spec.problems.get(key)
        if compiled is None:
            raise CodegenError(f"{name}: shrinking=True needs (4.5) with the horizon {h} as "
                               f"problems[{key!r}] (RAPSF.deployment_spec() compiles it)")
        libs += _check_compiled(compiled, f"{name}: the QP (4.5) with horizon {h}",
                                allow_external)
        Ph = _Problem(compiled, f"{name}_{key}",
                      f"the RAPSF QP (4.5) with the shrunk horizon {h} (Remark 4.6) "
                      f"{compiled.ocp.name!r}", name, accept_tol)
        layout = {k: (v["offset"], list(v["shape"])) for k, v in Ph.params.items()}
        if layout != {k: (v["offset"], list(v["shape"])) for k, v in P.params.items()}:
            raise CodegenError(f"{name}: (4.5) with horizon {h} has the parameters "
                               f"{sorted(layout)} with another layout than the main problem "
                               f"({sorted(P.params)}); build both with rapsf_problem")
        if list(Ph.vars.get("v", {}).get("shape", [])) != [nu, h]:
            raise CodegenError(f"{name}: (4.5) with horizon {h} must have the variable v "
                               f"of shape ({nu}, {h})")
        out[key] = Ph
    return out, libs


__all__ = ["EMITTABLE_TARGET", "casadi_dir", "emit_rapsf", "link_flags"]
