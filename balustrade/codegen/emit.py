"""Emit C sources from compiled CasADi problems, safety filters and plain functions.

Three entry points, each writing ``<name>_casadi.c/.h`` (CasADi's code generation,
``casadi.CodeGenerator`` with ``with_header``), balustrade's own ``<name>.c/.h`` (documented
entry points, see :mod:`balustrade.codegen.templates`) and ``<name>.json`` (a manifest the
Python runtime reads: sizes, offsets, status codes):

* :func:`emit_functions` / :func:`emit_function` — any plain function of the language
  (dynamics ``System.function``, ``h_f``, a value-function surrogate, their gradients):
  the C entry point is CasADi's ``<fn>(arg, res, iw, w, mem)`` with ``<fn>_work``,
  ``<fn>_incref``/``_checkout``/``_release``/``_decref``;
* :func:`emit_problem` — one compiled problem (e.g. (2.24)): ``<name>_solve(work, p)``;
* :func:`emit_pcbf` — the PCBF pair (2.24)+(2.23) as one call per control step,
  ``<name>_step(x, u_p, u_out, h_out, status, work)``, with the fallbacks of
  :mod:`balustrade.control.pcbf`.

Every compiled problem's target is asked first whether it can be emitted
(:meth:`~balustrade.backends.Target.emit_reason`, facts in :mod:`balustrade.backends.emittable`) and
every function graph is searched for Python callbacks
(:func:`~balustrade.codegen.support.check_no_callbacks`).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import casadi as ca
import numpy as np

from balustrade._checks import as_vector
from balustrade.backends.casadi_backend import CasadiCompiled
from balustrade.backends.emittable import c_attempts
from balustrade.codegen import status as S
from balustrade.codegen import templates as T
from balustrade.codegen.support import check_no_callbacks
from balustrade.control.pcbf import ZERO_TOL
from balustrade.dsl.sets import Box
from balustrade.errors import CodegenError, NonFiniteError, ShapeError

MANIFEST_VERSION = 1
#: scaled primal violation under which a solve that no retry made converge is reported as
#: BAL_FEASIBLE (a safe, possibly suboptimal point; the Python backend has a further,
#: non-emittable retry)
STALL_TOL = 1e-8


@dataclass
class Emitted:
    """What an ``emit_*`` call wrote: the folder, the sources, and the manifest."""

    name: str
    out_dir: Path
    sources: list[Path]
    headers: list[Path]
    manifest: dict = field(repr=False)
    libraries: tuple[str, ...] = ()

    @property
    def kind(self) -> str:
        return str(self.manifest["kind"])


# -- helpers ---------------------------------------------------------------------------
def _check_identifier(name: str, what: str = "name") -> str:
    if not (isinstance(name, str) and name.isidentifier() and name.isascii()):
        raise CodegenError(f"{what} {name!r} must be an ASCII C identifier")
    return name


def _out_dir(out_dir: str | Path, name: str) -> Path:
    """Create ``out_dir`` (and parents) and check that it is a writable folder, so that a
    bad path is reported with its name before CasADi generates anything."""
    if not isinstance(out_dir, (str, os.PathLike)):
        raise CodegenError(f"{name}: out_dir must be a path, got {type(out_dir).__name__}")
    path = Path(out_dir)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:  # a parent (or the path itself) is a file, permissions, ...
        raise CodegenError(f"{name}: cannot create the output folder {str(path)!r}: "
                           f"{exc.strerror or exc}") from exc
    if not path.is_dir() or not os.access(path, os.W_OK | os.X_OK):
        raise CodegenError(f"{name}: the output folder {str(path)!r} is not a writable "
                           "folder")
    return path


def _check_accept_tol(name: str, accept_tol: float | None) -> None:
    if accept_tol is None:
        return
    try:
        tol = float(accept_tol)
    except (TypeError, ValueError) as exc:
        raise CodegenError(f"{name}: accept_tol must be a number, got {accept_tol!r}") from exc
    if not np.isfinite(tol) or tol < 0:
        raise CodegenError(f"{name}: accept_tol must be finite and >= 0, got {accept_tol!r}")


def _check_dynamics(name: str, dynamics: object) -> None:
    if dynamics is not None and not isinstance(dynamics, ca.Function):
        raise CodegenError(f"{name}: dynamics must be a casadi.Function (e.g. "
                           f"system.function), got {type(dynamics).__name__}")


def _c_array(values: np.ndarray | list[float], min_len: int = 1) -> str:
    vals = [float(v) for v in np.asarray(values, dtype=float).reshape(-1)]
    if len(vals) < min_len:
        vals += [0.0] * (min_len - len(vals))
    return "{" + ", ".join(_c_double(v) for v in vals) + "}"


def _c_double(v: float) -> str:
    if np.isnan(v):
        return "NAN"
    if np.isinf(v):
        return "INFINITY" if v > 0 else "-INFINITY"
    return repr(float(v))


def _renamed(fn: ca.Function, name: str) -> ca.Function:
    """``fn`` under the C symbol ``name``, with dense inputs and outputs (the C entry point
    then reads and writes plain column-major arrays; structural zeros are written as 0).
    Solvers and other non-expression functions are only renamed when needed."""
    if fn.is_a("SXFunction") or fn.is_a("MXFunction"):
        sym = ca.SX.sym if fn.is_a("SXFunction") else ca.MX.sym
        args = [sym(fn.name_in(i), fn.size1_in(i), fn.size2_in(i)) for i in range(fn.n_in())]
        outs = [ca.densify(o) for o in fn.call(args)]
        return ca.Function(name, args, outs, fn.name_in(), fn.name_out())
    if fn.name() == name:
        return fn
    args = fn.mx_in()
    return ca.Function(name, args, fn.call(args), fn.name_in(), fn.name_out())


def _generate(functions: dict[str, ca.Function], name: str, out_dir: Path) -> list[Path]:
    """Run CasADi's code generator on ``functions`` (C symbol -> Function) into
    ``out_dir/<name>_casadi.c/.h`` and make the C warning-clean."""
    out_dir.mkdir(parents=True, exist_ok=True)
    cg_name = f"{name}_casadi"
    cg = ca.CodeGenerator(cg_name, {"with_header": True})
    for sym, fn in functions.items():
        check_no_callbacks(fn, f"{name}: function {sym!r}")
        cg.add(_renamed(fn, sym))
    try:
        cg.generate(str(out_dir) + "/")
    except RuntimeError as exc:  # pragma: no cover - CasADi-internal failures
        raise CodegenError(f"{name}: CasADi code generation failed: {exc}") from exc
    c_path, h_path = out_dir / f"{cg_name}.c", out_dir / f"{cg_name}.h"
    c_path.write_text(T.PRAGMA + c_path.read_text())
    return [c_path, h_path]


def _kkt_function(c: CasadiCompiled, sym: str) -> ca.Function:
    """The solver's own convergence measures at a point, as a C-emittable function:
    ``pr_inf`` = largest bound/constraint violation, ``du_inf`` = ``‖∇f + Jᵀλ_g + λ_x‖∞``,
    ``feas`` = largest violation with constraint rows scaled by ``1 + |g|`` (the test for
    ``BAL_FEASIBLE`` after all retries)."""
    w, p, f, g = c.nlp["x"], c.nlp["p"], c.nlp["f"], c.nlp["g"]
    cls = type(w)
    lam_x = cls.sym("lam_x", w.numel())
    lam_g = cls.sym("lam_g", g.numel())
    lag = f + ca.dot(lam_g, g) if g.numel() else f
    du = ca.norm_inf(ca.gradient(lag, w) + lam_x)
    viol = [ca.fmax(w - ca.DM(c.ubx), 0), ca.fmax(ca.DM(c.lbx) - w, 0)]
    if g.numel():
        viol += [ca.fmax(g - ca.DM(c.ubg), 0), ca.fmax(ca.DM(c.lbg) - g, 0)]
    pr = ca.mmax(ca.vertcat(*viol, 0))
    scaled = viol[:2]
    if g.numel():
        scaled += [ca.fmax(g - ca.DM(c.ubg), ca.DM(c.lbg) - g) / (1 + ca.fabs(g))]
    feas = ca.mmax(ca.vertcat(*scaled, 0))
    return ca.Function(sym, [w, p, lam_x, lam_g], [pr, du, feas],
                       ["x", "p", "lam_x", "lam_g"], ["pr_inf", "du_inf", "feas"])


def _check_compiled(c: object, what: str, allow_external: bool) -> tuple[str, ...]:
    if not isinstance(c, CasadiCompiled):
        raise CodegenError(f"{what}: C code generation needs a problem compiled on the "
                           f"CasADi backend, got {type(c).__name__} (compile it for the "
                           "'fast-sqp' target: balustrade.backends.compile(ocp, 'fast-sqp'))")
    reason = c.target.emit_reason(allow_external)
    if reason is not None:
        raise CodegenError(f"{what}: {reason}")
    libs = c.target.c_libraries()
    check_no_callbacks(c.solver, what)
    return libs


def _controller_pair(controller: object, name: str, kind: str, first: object, second: object,
                     labels: tuple[str, str], allow_external: bool
                     ) -> tuple[CasadiCompiled, CasadiCompiled, Box, tuple[str, ...]]:
    """The two compiled problems and the box U of a two-problem controller, checked for C."""
    U = getattr(controller, "U", None)
    if first is None or second is None or U is None:
        raise CodegenError(f"{name}: expected a {kind}, got {type(controller).__name__}")
    libs = _check_compiled(first, f"{name}: {labels[0]}", allow_external)
    libs += _check_compiled(second, f"{name}: {labels[1]}", allow_external)
    if not isinstance(U, Box):
        raise CodegenError(f"{name}: the C step projects onto U by clipping, so U must be a "
                           f"Box, got {type(U).__name__}")
    return first, second, U, libs


def _require(name: str, needed: dict[str, tuple[dict, list[str]]], hint: str) -> None:
    """Raise a CodegenError naming the parameters/variables a generated step relies on."""
    for what, (have, names) in needed.items():
        missing = [n for n in names if n not in have]
        if missing:
            raise CodegenError(f"{name}: the {what}s {missing} are missing ({hint})")


class _Problem:
    """The C pieces of one compiled problem under the C prefix ``P``."""

    def __init__(self, c: CasadiCompiled, P: str, title: str, module: str,
                 accept_tol: float | None = None):
        self.c, self.P, self.title, self.module = c, P, title, module
        self.nw = int(c.nlp["x"].numel())
        self.np = int(c.nlp["p"].numel())
        self.ng = int(c.nlp["g"].numel())
        self.tol_pr = float(c.options.get("tol_pr", 1e-6))
        self.tol_du = float(c.options.get("tol_du", 1e-6))
        self.accept_tol = STALL_TOL if accept_tol is None else float(accept_tol)
        self.solvers = [(f"{P}_nlp", c.solver_name, dict(c.options))]
        # the cold-start retries the emitted C runs (backends.emittable.c_attempts): the
        # same solver again reuses its function, other settings get their own
        self.retry_labels, self.retry_docs = [], []
        for k, (plugin, over, label) in enumerate(c_attempts(c.solver_name, c.options)):
            sym = f"{P}_nlp" if plugin == c.solver_name and not over else \
                f"{P}_nlp_retry{k + 1}"
            self.solvers.append((sym, plugin, {**c.options, **over}))
            self.retry_labels.append(label)
            self.retry_docs.append(" ".join([plugin, *(f"{o} {v!r}" for o, v in over.items())])
                                   if over else f"{plugin} again")
        self.layout = c.layout  # the solver's x: the user's variables, then epigraph blocks
        self.vars = self.layout.to_dict()
        self.params = c.ocp.parameter_layout.to_dict()  # with declared values as "default"
        init = self.layout.initial()
        self.init = np.where(np.isfinite(init), init, 0.0)

    def functions(self) -> dict[str, ca.Function]:
        out = {sym: ca.nlpsol(sym, plugin, self.c.nlp, opts)
               for sym, plugin, opts in self.solvers}
        out[f"{self.P}_kkt"] = _kkt_function(self.c, f"{self.P}_kkt")
        return out

    def _solver_code(self) -> dict[str, str]:
        """C snippets: size macros, memory checkout/release, dispatch of attempts."""
        P, syms = self.P, [sym for sym, _, _ in self.solvers]
        uniq = list(dict.fromkeys(syms))
        sz = ""
        for key in ("ARG", "RES", "IW", "W"):
            expr = f"{uniq[0]}_SZ_{key}"
            for sym in uniq[1:]:
                expr = f"{P}_MAX2({expr}, {sym}_SZ_{key})"
            sz += f"#define {P}_SZ_{key} {expr}\n"
        init, fini, dispatch = "", "", ""
        for k, sym in enumerate(syms):
            first = syms.index(sym)
            if first < k:  # the same function again: reuse its memory
                init += f"  wk->mem[{k}] = wk->mem[{first}];\n"
            else:
                init += (f"  {sym}_incref();\n  wk->mem[{k}] = {sym}_checkout();\n"
                         f"  if (wk->mem[{k}] < 0) {{\n    {sym}_decref();\n")
                for j in range(k - 1, -1, -1):
                    if syms.index(syms[j]) == j:
                        init += f"    {syms[j]}_release(wk->mem[{j}]);\n    {syms[j]}_decref();\n"
                init += "    return -1;\n  }\n"
        for k in range(len(syms) - 1, -1, -1):
            if syms.index(syms[k]) == k:
                fini += f"  {syms[k]}_release(wk->mem[{k}]);\n  {syms[k]}_decref();\n"
        for k, sym in enumerate(syms):
            dispatch += (f"    case {k}:\n      flag = {sym}(wk->arg, wk->res, wk->iw, wk->w, "
                         f"wk->mem[{k}]);\n      break;\n")
        dispatch += "    default:\n      return BAL_EVAL_ERROR;\n"
        doc = "; ".join(self.retry_docs)
        return {"sz_defs": sz, "solver_init": init, "solver_fini": fini,
                "dispatch": dispatch, "retry_doc": doc, "n_solvers": str(len(syms))}

    def header(self) -> str:
        pdoc = "".join(f"\n *   {n}: offset {v['offset']}, shape {tuple(v['shape'])}"
                       for n, v in self.params.items()) or " none"
        vdoc = "".join(f"\n *   {n}: offset {v['offset']}, shape {tuple(v['shape'])}"
                       for n, v in self.vars.items())
        n_user = self.layout.user_size
        if self.nw > n_user:
            vdoc += (f"\n *   (epigraph variables of non-smooth costs: offset {n_user}"
                     f", {self.nw - n_user} values)")
        offsets = "".join(f"#define {self.P}_P_{n} {v['offset']}\n"
                          for n, v in self.params.items())
        offsets += "".join(f"#define {self.P}_W_{n} {v['offset']}\n"
                           for n, v in self.vars.items())
        code = self._solver_code()
        return T.PROBLEM_H.substitute(P=self.P, title=self.title, np=self.np, nw=self.nw,
                                      retry_doc=code["retry_doc"], sz_defs=code["sz_defs"],
                                      n_solvers=code["n_solvers"],
                                      ng=self.ng, param_doc=pdoc, var_doc=vdoc,
                                      tol_pr=f"{self.tol_pr:g}", tol_du=f"{self.tol_du:g}",
                                      accept_tol=f"{self.accept_tol:g}", offsets=offsets,
                                      name=self.module)

    def source(self) -> str:
        code = self._solver_code()
        return T.PROBLEM_C.substitute(
            P=self.P, solver_init=code["solver_init"], solver_fini=code["solver_fini"],
            dispatch=code["dispatch"], n_solvers=code["n_solvers"], nw=self.nw,
            ng1=max(self.ng, 1), lbx=_c_array(self.c.lbx),
            ubx=_c_array(self.c.ubx), lbg=_c_array(self.c.lbg), ubg=_c_array(self.c.ubg),
            init=_c_array(self.init), n_user=self.layout.user_size,
            tol_pr=_c_double(self.tol_pr),
            tol_du=_c_double(self.tol_du), accept_tol=_c_double(self.accept_tol))

    def manifest(self) -> dict:
        return {"prefix": self.P, "title": self.title, "np": self.np, "nw": self.nw,
                "ng": self.ng, "n_user": self.layout.user_size, "variables": self.vars,
                "parameters": self.params, "tol_pr": self.tol_pr, "tol_du": self.tol_du,
                "accept_tol": self.accept_tol,
                "retries": list(self.retry_labels),
                "solver": self.c.solver_name, "qpsol": self.c.options.get("qpsol")}


def _write_module(name: str, out_dir: Path, what: str, header_body: str, source_body: str,
                  casadi_files: list[Path], manifest: dict, libs: tuple[str, ...]) -> Emitted:
    NAME = name.upper()
    h = out_dir / f"{name}.h"
    c = out_dir / f"{name}.c"
    h.write_text(T.HEADER_TOP.substitute(name=name, NAME=NAME, what=what,
                                         solve_status=S.c_defines(S.SOLVE)) + header_body
                 + T.HEADER_BOTTOM.substitute(NAME=NAME))
    c.write_text(T.SOURCE_TOP.substitute(name=name) + source_body)
    manifest = {"version": MANIFEST_VERSION, "name": name, "casadi": ca.__version__,
                "libraries": list(libs), **manifest,
                "status_codes": S.manifest(S.SOLVE)}
    (out_dir / f"{name}.json").write_text(json.dumps(manifest, indent=1))
    return Emitted(name, out_dir, [c, casadi_files[0]], [h, casadi_files[1]], manifest, libs)


# -- public API ------------------------------------------------------------------------
def emit_functions(functions: dict[str, ca.Function] | ca.Function, name: str,
                   out_dir: str | Path) -> Emitted:
    """Emit plain CasADi functions (dynamics, ``h_f``, a value-function surrogate, their
    gradients, ...) as C. ``functions`` maps the C symbol of each function to it (a single
    Function is emitted under its own name). Entry points are CasADi's: for each symbol
    ``fn``: ``int fn(const casadi_real** arg, casadi_real** res, casadi_int* iw,
    casadi_real* w, int mem)`` with ``fn_work``, ``fn_incref``, ``fn_checkout``,
    ``fn_release``, ``fn_decref`` and the ``fn_SZ_ARG/RES/IW/W`` macros."""
    _check_identifier(name)
    if isinstance(functions, ca.Function):
        functions = {functions.name(): functions}
    if not isinstance(functions, dict):
        raise CodegenError(f"{name}: expected a casadi.Function or a dict C symbol -> "
                           f"casadi.Function, got {type(functions).__name__}")
    if not functions:
        raise CodegenError(f"{name}: no functions to emit")
    for sym, fn in functions.items():
        _check_identifier(sym, f"{name}: function symbol")
        if not isinstance(fn, ca.Function):
            raise CodegenError(f"{name}: {sym!r} is a {type(fn).__name__}, expected a "
                               "casadi.Function")
        if fn.has_free():
            raise CodegenError(f"{name}: function {sym!r} has free symbols "
                               f"{fn.get_free()}; make them inputs")
    out_dir = _out_dir(out_dir, name)
    files = _generate(dict(functions), name, out_dir)
    info = {sym: {"n_in": fn.n_in(), "n_out": fn.n_out(),
                  "in": [[fn.size1_in(i), fn.size2_in(i)] for i in range(fn.n_in())],
                  "out": [[fn.size1_out(i), fn.size2_out(i)] for i in range(fn.n_out())],
                  "name_in": fn.name_in(), "name_out": fn.name_out()}
            for sym, fn in functions.items()}
    body = "/* Plain functions: see the CasADi entry points declared in " \
           f"{name}_casadi.h: {', '.join(functions)} */\n\n"
    return _write_module(name, out_dir, "plain CasADi functions", body,
                         "/* nothing beyond the CasADi-generated functions */\n",
                         files, {"kind": "functions", "functions": info}, ())


def emit_function(fn: ca.Function, name: str, out_dir: str | Path) -> Emitted:
    """:func:`emit_functions` for one function, emitted under the C symbol ``name``."""
    return emit_functions({name: fn}, name, out_dir)


def emit_problem(compiled: CasadiCompiled, name: str, out_dir: str | Path,
                 allow_external: bool = False, accept_tol: float | None = None) -> Emitted:
    """Emit one compiled problem (e.g. the slack problem (2.24)) with the entry point
    ``int <name>_solve(<name>_work* wk, const casadi_real* p)``: parameters ``p`` stacked
    in declaration order, warm start in ``wk->x0/lam_x0/lam_g0``, outputs ``wk->x``
    (full primal solution; ``<name>_W_u`` is the offset of ``u``, so ``u_{0|k}`` is
    ``wk->x[<name>_W_u]``), ``wk->f`` (value), return value = status (``BAL_*``).

    ``BAL_OK`` uses the solver's own tolerances ``tol_pr``/``tol_du``. Attempts that do not
    converge are retried from a cold start with the retries of the target that emitted C
    runs (:func:`~balustrade.backends.emittable.c_attempts`; the backend's last resort of
    the fast-sqp target cannot be emitted). If
    none converges and the last attempt's scaled constraint violation is ``<= accept_tol``
    (default ``1e-8``) the status is ``BAL_FEASIBLE``: safe to apply, possibly suboptimal."""
    _check_identifier(name)
    _check_accept_tol(name, accept_tol)
    libs = _check_compiled(compiled, name, allow_external)
    out_dir = _out_dir(out_dir, name)
    prob = _Problem(compiled, name + "_p", compiled.ocp.name, name, accept_tol)
    files = _generate(prob.functions(), name, out_dir)
    return _write_module(name, out_dir, f"the problem {compiled.ocp.name!r}", prob.header(),
                         prob.source(), files,
                         {"kind": "problem", "problems": {"problem": prob.manifest()}}, libs)


def emit_pcbf(controller: object, name: str, out_dir: str | Path,
              dynamics: ca.Function | None = None, allow_external: bool = False,
              accept_tol: float | None = None) -> Emitted:
    """Emit the PCBF safety filter (2.24)+(2.23) of a
    :class:`~balustrade.control.pcbf.PCBFSafetyFilter` built on the CasADi backend as one
    C call per control step: ``<name>_step(x, u_p, u_out, h_out, status, work)``.

    ``dynamics`` (e.g. ``system.function``) is emitted too, as ``<name>_dynamics``, for
    the closed-loop example ``main.c`` (:func:`write_example`). The fallback "projected
    proposal" clips to ``U``, which must be a :class:`~balustrade.dsl.sets.Box`.

    Solves are accepted and retried as in :func:`emit_problem` (``accept_tol``), which
    mirrors :class:`~balustrade.backends.casadi_backend.CasadiCompiled` except for the
    final, non-emittable retry of the fast-sqp target's chain.
    """
    _check_identifier(name)
    _check_accept_tol(name, accept_tol)
    _check_dynamics(name, dynamics)
    out_dir = _out_dir(out_dir, name)
    slack, filt, U, libs = _controller_pair(
        controller, name, "PCBFSafetyFilter (attributes slack, filter, U)",
        getattr(controller, "slack", None), getattr(controller, "filter", None),
        ("slack problem (2.24)", "filter problem (2.23)"), allow_external)
    s = _Problem(slack, f"{name}_slack", f"slack problem (2.24) {slack.ocp.name!r}", name,
                 accept_tol)
    f = _Problem(filt, f"{name}_filter", f"filter problem (2.23) {filt.ocp.name!r}", name,
                 accept_tol)
    _require(name, {"slack parameter": (s.params, ["x0"]),
                    "slack variable": (s.vars, ["u", "xi", "xi_N"]),
                    "filter parameter": (f.params, ["x0", "u_p", "xi", "xi_N"]),
                    "filter variable": (f.vars, ["u"])},
             "build the problems of the PCBF pair with balustrade.problems.pcbf")
    if np.prod(s.vars["xi"]["shape"]) != np.prod(f.params["xi"]["shape"]):
        raise CodegenError(f"{name}: slack xi {s.vars['xi']['shape']} and filter parameter xi "
                           f"{f.params['xi']['shape']} differ")
    system = slack.ocp.system
    nx, nu, N = system.nx, system.nu, slack.ocp.N
    if filt.ocp.N != N or s.vars["u"]["shape"] != [nu, N]:
        raise CodegenError(f"{name}: horizons of (2.24) ({N}) and (2.23) ({filt.ocp.N}) differ")
    # warm start of (2.23) before its first success: variables shared by name with (2.24)
    copies = []
    for vn, lay in f.vars.items():
        if vn in s.vars and s.vars[vn]["shape"] == lay["shape"]:
            copies.append((s.vars[vn]["offset"], lay["offset"], int(np.prod(lay["shape"]))))
    copy_shared = "".join(
        f"    memcpy(wk->filter.x0 + {d}, wk->slack.x + {src}, {n} * sizeof(casadi_real));\n"
        for src, d, n in copies)
    Q = name
    functions = {**s.functions(), **f.functions()}
    if dynamics is not None:
        functions[f"{Q}_dynamics"] = dynamics
    files = _generate(functions, name, out_dir)
    header = s.header() + f.header() + T.PCBF_H.substitute(
        Q=Q, nx=nx, nu=nu, N=N, pcbf_status=S.c_defines(S.PCBF), zero_tol=_c_double(ZERO_TOL))
    source = s.source() + f.source() + T.PCBF_C.substitute(
        Q=Q, u_lb=_c_array(U.lb), u_ub=_c_array(U.ub), s_p_x0=s.params["x0"]["offset"],
        f_p_x0=f.params["x0"]["offset"], f_p_u_p=f.params["u_p"]["offset"],
        f_p_xi=f.params["xi"]["offset"], f_p_xi_N=f.params["xi_N"]["offset"],
        n_xi=int(np.prod(s.vars["xi"]["shape"])), s_w_xi=s.vars["xi"]["offset"],
        s_w_xi_N=s.vars["xi_N"]["offset"], s_w_u=s.vars["u"]["offset"],
        f_w_u=f.vars["u"]["offset"], copy_shared=copy_shared)
    manifest = {"kind": "pcbf", "nx": nx, "nu": nu, "N": N,
                "eps": float(getattr(controller, "eps", 0.0)),
                "U": {"lb": list(map(float, U.lb)), "ub": list(map(float, U.ub))},
                "problems": {"slack": s.manifest(), "filter": f.manifest()},
                "dynamics": dynamics is not None,
                "pcbf_status": S.manifest(S.PCBF)}
    return _write_module(name, out_dir, "the PCBF safety filter (2.24)+(2.23)", header,
                         source, files, manifest, tuple(sorted(set(libs))))


def write_example(emitted: Emitted, x_init: np.ndarray, u_p: np.ndarray | float,
                  steps: int = 30) -> list[Path]:
    """Write ``main.c`` (a closed loop of the emitted PCBF step on the emitted dynamics
    from each row of ``x_init`` with a constant proposal ``u_p``, printing the trajectory
    and timing the step and the dynamics) and a ``Makefile`` next to the sources."""
    m = emitted.manifest
    if m.get("kind") != "pcbf" or not m.get("dynamics"):
        raise CodegenError(f"{emitted.name}: the example needs a PCBF filter emitted with "
                           "its dynamics (emit_pcbf(..., dynamics=system.function))")
    nx, nu = m["nx"], m["nu"]
    x_init = np.atleast_2d(np.asarray(x_init, dtype=float))
    if x_init.ndim != 2 or x_init.shape[1] != nx:
        raise ShapeError(f"{emitted.name}: initial states x_init", f"(n, {nx})",
                         x_init.shape, what="shape")
    u_p = np.asarray(u_p, dtype=float).reshape(-1)
    if u_p.size == 1:
        u_p = np.broadcast_to(u_p, (nu,))
    u_p = as_vector(u_p, f"{emitted.name}: proposal u_p", nu)
    if not np.all(np.isfinite(x_init)):
        raise NonFiniteError(f"{emitted.name}: initial states x_init contain NaN or inf "
                             f"(shape {x_init.shape})")
    if int(steps) != steps or steps < 1:
        raise CodegenError(f"{emitted.name}: steps must be a positive integer, got {steps!r}")
    rows = ",\n  ".join(_c_array(r) for r in x_init)
    main = T.MAIN_C.substitute(Q=emitted.name, name=emitted.name, n_init=len(x_init),
                               steps=int(steps), x_init="{\n  " + rows + "\n}",
                               u_p=_c_array(u_p))
    main_path = emitted.out_dir / "main.c"
    main_path.write_text(main)
    mk = emitted.out_dir / "Makefile"
    mk.write_text(T.MAKEFILE.substitute(name=emitted.name))
    return [main_path, mk]


def emit_approximate(controller: object, name: str, out_dir: str | Path,
                     dynamics: ca.Function | None = None, allow_external: bool = False,
                     accept_tol: float | None = None) -> Emitted:
    """Emit Algorithm 7.5 of an
    :class:`~balustrade.control.approximate.ApproximatePCBFFilter` (built with
    ``target="fast-sqp"``) as one C call per control step:
    ``<name>_step(x, u_p, u_out, h_out, status, work)`` — the certification shortcut
    ``u_p ∈ U ∧ ĥ(f(x, u_p)) <= 0``, else the maximal decrease (7.6) by the same screened
    multi-start (candidates ``clip(0)``, ``clip(u_p)`` and the controller's grid; local
    solves from the ``n_local`` best distinct ones), then the filter (7.5) warm-started
    at the (7.6) minimizer, with the controller's fallbacks. ``ĥ`` and ``ĥ(f(x, u))`` are
    emitted as ``<name>_h`` and ``<name>_h_next``; ``U`` must be a Box."""
    _check_identifier(name)
    _check_accept_tol(name, accept_tol)
    _check_dynamics(name, dynamics)
    out_dir = _out_dir(out_dir, name)
    dec, filt, U, libs = _controller_pair(
        controller, name, "ApproximatePCBFFilter (attributes decrease, filter, U)",
        getattr(getattr(controller, "decrease", None), "compiled", None),
        getattr(controller, "filter", None),
        ("maximal decrease problem (7.6)", "filter problem (7.5)"), allow_external)
    system = controller.system
    d = _Problem(dec, f"{name}_dec", f"maximal decrease (7.6) {dec.ocp.name!r}", name,
                 accept_tol)
    f = _Problem(filt, f"{name}_filter", f"filter (7.5) {filt.ocp.name!r}", name, accept_tol)
    _require(name, {"(7.6) parameter": (d.params, ["x0"]), "(7.6) variable": (d.vars, ["u"]),
                    "(7.5) parameter": (f.params, ["x0", "u_p", "dh", "rho"]),
                    "(7.5) variable": (f.vars, ["u"])},
             "build the problems with balustrade.problems.approximate")
    grid = np.atleast_2d(np.asarray(controller.decrease.grid, dtype=float))
    x, u = ca.SX.sym("x", system.nx), ca.SX.sym("u", system.nu)
    h = controller.h
    functions = {**d.functions(), **f.functions(),
                 f"{name}_h": ca.Function(f"{name}_h", [x], [h(x)], ["x"], ["h"]),
                 f"{name}_h_next": ca.Function(f"{name}_h_next", [x, u], [h(system(x, u))],
                                               ["x", "u"], ["h_next"])}
    if dynamics is not None:
        functions[f"{name}_dynamics"] = dynamics
    files = _generate(functions, name, out_dir)
    A = name
    nc = len(grid) + 2
    header = d.header() + f.header() + T.APPROX_H.substitute(
        A=A, nx=system.nx, nu=system.nu, nc=nc, n_local=int(controller.decrease.n_local),
        approx_status=S.c_defines(S.APPROX),
        rho=_c_double(controller.rho),
        exact_shortcut=int(bool(getattr(controller, "exact_shortcut", False))))
    rows = ",\n  ".join(_c_array(r) for r in grid)
    source = d.source() + f.source() + T.APPROX_C.substitute(
        A=A, u_lb=_c_array(U.lb), u_ub=_c_array(U.ub), grid="{\n  " + rows + "\n}",
        certify=int(bool(controller.certify)), d_w_u=d.vars["u"]["offset"],
        d_p_x0=d.params["x0"]["offset"], f_p_x0=f.params["x0"]["offset"],
        f_p_u_p=f.params["u_p"]["offset"], f_p_dh=f.params["dh"]["offset"],
        f_p_rho=f.params["rho"]["offset"], f_w_u=f.vars["u"]["offset"])
    manifest = {"kind": "approximate", "nx": system.nx, "nu": system.nu, "n_candidates": nc,
                "n_local": int(controller.decrease.n_local), "rho": float(controller.rho),
                "certify": bool(controller.certify),
                "U": {"lb": list(map(float, U.lb)), "ub": list(map(float, U.ub))},
                "problems": {"dec": d.manifest(), "filter": f.manifest()},
                "dynamics": dynamics is not None,
                "exact_shortcut": bool(getattr(controller, "exact_shortcut", False)),
                "approx_status": S.manifest(S.APPROX)}
    return _write_module(name, out_dir, "Algorithm 7.5, the approximate PCBF filter "
                         "(7.5)+(7.6)", header, source, files, manifest,
                         tuple(sorted(set(libs))))
