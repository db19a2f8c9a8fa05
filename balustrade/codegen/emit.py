"""Emit C sources from compiled CasADi problems, safety filters and plain functions.

Each entry point writes, into ``out_dir``: ``<name>_casadi.c/.h`` (CasADi's code generation,
``casadi.CodeGenerator`` with ``with_header``: the solvers and functions), ``bal/`` (balustrade's
static C, the same files for every module: :mod:`~balustrade.codegen.cfiles`),
``<name>_config.h`` (the numbers of this module: sizes, offsets, bounds, tolerances, status
codes), ``<name>.h``/``<name>.c`` (glue instantiating the static C under the module's symbol
prefixes) and ``<name>.json`` (a manifest the Python runtime reads: sizes, offsets, status
codes):

* :func:`emit_functions` / :func:`emit_function` — any plain function of the language
  (dynamics ``System.function``, ``h_f``, a value-function surrogate, their gradients):
  the C entry point is CasADi's ``<fn>(arg, res, iw, w, mem)`` with ``<fn>_work``,
  ``<fn>_incref``/``_checkout``/``_release``/``_decref``;
* :func:`emit_problem` — one compiled problem (e.g. (2.24)): ``<name>_p_solve(work, p)``;
  :func:`emit_problems` — several, e.g. those of Algorithm 5.2: ``<name>_<key>_solve``;
* :func:`emit_pcbf` — the PCBF pair (2.24)+(2.23) as one call per control step,
  ``<name>_step(x, u_p, u_out, h_out, status, work)``, with the fallbacks of
  :mod:`balustrade.control.pcbf`;
* :func:`emit_approximate` — Algorithm 7.5 ((7.6) then (7.5)) as one call per control step.

The controllers are read through their typed deployment specs
(:mod:`balustrade.control.deploy`). Every compiled problem's target is asked first whether it
can be emitted (:meth:`~balustrade.backends.Target.emit_reason`, facts in
:mod:`balustrade.backends.emittable`) and every function graph is searched for Python
callbacks (:func:`~balustrade.codegen.support.check_no_callbacks`).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import casadi as ca
import numpy as np

from balustrade._checks import as_vector
from balustrade.backends.casadi_backend import (
    EMITTED_STOP_OPTIONS,
    CasadiCompiled,
    chain_solver_index,
    complementarity_expr,
)
from balustrade.backends.emittable import (
    ACCEPTABLE_STOP,
    RETURN_STATUS_SUFFIX,
    STATUS_OPTIONS,
    c_libraries,
    c_retries,
    include_subdirs,
    once_per_file,
    retries_link_libraries,
    status_accessors,
)
from balustrade.backends.solution import FEASIBILITY_TOL
from balustrade.codegen import cfiles as C
from balustrade.codegen import status as S
from balustrade.codegen.support import check_no_callbacks
from balustrade.control.deploy import ApproximateDeployment, PCBFDeployment, ProblemsDeployment
from balustrade.control.shifted import ShiftedCertificate
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
    #: balustrade's static C copied into ``out_dir/bal/`` (included by the sources)
    static: list[Path] = field(default_factory=list, repr=False)

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
    classes = {}  # C symbol -> CasADi class of the function generated under it
    for sym, fn in functions.items():
        check_no_callbacks(fn, f"{name}: function {sym!r}")
        renamed = _renamed(fn, sym)
        classes[sym] = renamed.class_name()
        cg.add(renamed)
    try:
        cg.generate(str(out_dir) + "/")
    except RuntimeError as exc:  # pragma: no cover - CasADi-internal failures
        raise CodegenError(f"{name}: CasADi code generation failed: {exc}") from exc
    c_path, h_path = out_dir / f"{cg_name}.c", out_dir / f"{cg_name}.h"
    # the accessors of the interior-point solver's own return status (its acceptable stop
    # is optimal_inaccurate, as in the backend: bal/problem.c, emittable.ACCEPTABLE_STOP)
    try:
        c_text, h_text = status_accessors(once_per_file(c_path.read_text()),
                                          h_path.read_text(), classes)
    except ValueError as exc:  # pragma: no cover - another CasADi's generated C
        raise CodegenError(f"{name}: {exc}") from exc
    c_path.write_text(C.static_text("casadi_prologue.h") + c_text)
    h_path.write_text(h_text)
    return [c_path, h_path]


#: the NLP lowering the C is generated from (:data:`~balustrade.backends.casadi_backend.
#: LOWERINGS`): ``"compact"`` maps one stage function of the dynamics over the horizon, so
#: its derivatives appear once in the C (cart-pole PCBF pair: ~10× less C, builds in
#: seconds instead of a minute; docs/deploy_c.md)
EMIT_LOWERING = "compact"


def _kkt_function(c: CasadiCompiled, sym: str, lowering: str | None = None,
                  lowered: tuple[dict, dict] | None = None) -> ca.Function:
    """The solver's own convergence measures at a point, as a C-emittable function:
    ``pr_inf`` = largest bound/constraint violation, ``du_inf`` = ``‖∇f + Jᵀλ_g + λ_x‖∞``
    (where :meth:`~balustrade.backends.casadi_backend.CasadiCompiled.complementarity_weight`
    is not ``None``, at least the complementarity error times that weight, so the C's
    ``du_inf < P_TOL_DU`` also requires the backend's complementarity test),
    ``feas`` = largest violation with constraint rows scaled by ``1 + |g|`` (the test for
    ``BAL_FEASIBLE`` after all retries); on the NLP of ``lowering`` (default: the
    solver's own), or on ``lowered`` = ``(nlp, derivatives)`` when given."""
    if lowered is not None:  # given: (nlp, derivatives), e.g. the staged compact lowering
        nlp, derivatives = lowered
    else:
        nlp, derivatives = (c.nlp, getattr(c, "derivatives", {})) if lowering is None \
            else c.lowered(lowering)
    w, p, f, g = nlp["x"], nlp["p"], nlp["f"], nlp["g"]
    jac_fg = derivatives.get("jac_fg")
    if jac_fg is not None:  # reuse the solvers' Jacobian (its C exists once already)
        w, p = ca.MX.sym("x", w.numel()), ca.MX.sym("p", p.numel())
        f, grad_f, g, jac_g = jac_fg(w, p)
    cls = type(w)
    lam_x = cls.sym("lam_x", w.numel())
    lam_g = cls.sym("lam_g", g.numel())
    if jac_fg is not None:
        grad_lag = grad_f + (ca.mtimes(jac_g.T, lam_g) if g.numel() else 0)
    else:
        grad_lag = ca.gradient(f + ca.dot(lam_g, g) if g.numel() else f, w)
    du = ca.norm_inf(grad_lag + lam_x)
    weight = c.complementarity_weight()
    if weight is not None:  # P_TOL_DU also bounds the complementarity (scaled): as the backend
        du = ca.fmax(du, weight * complementarity_expr(c, w, g, lam_x, lam_g))
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


def _spec(controller: object, name: str, cls: type, kind: str) -> object:
    """The typed deployment spec (:mod:`balustrade.control.deploy`) of ``controller`` (or
    ``controller`` itself if it is one), else a CodegenError naming what was expected."""
    if isinstance(controller, cls):
        return controller
    get = getattr(controller, "deployment_spec", None)
    spec = get() if callable(get) else None
    if not isinstance(spec, cls):
        raise CodegenError(f"{name}: expected a {kind} (or its deployment_spec(), a "
                           f"{cls.__name__}), got {type(controller).__name__}")
    return spec


def _controller_pair(name: str, first: object, second: object, U: object,
                     labels: tuple[str, str], allow_external: bool
                     ) -> tuple[CasadiCompiled, CasadiCompiled, Box, tuple[str, ...]]:
    """The two compiled problems and the box U of a two-problem step, checked for C."""
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


def c_solver_options(plugin: str, opts: dict) -> dict:
    """The ``nlpsol`` options of an emitted attempt: ``opts``, the options the Python backend
    runs that attempt with (the compiled problem's for its own plugin, ``CasadiCompiled.
    _retry_options`` for a retry on another), plus what the C needs to read the solver's
    verdict (``STATUS_OPTIONS``: ``error_on_fail``) — but not the stopping rule of the
    emitted targets (``EMITTED_STOP_OPTIONS``), which an attempt carries only when Python's
    does (the retries of an as-emitted target). So C and Python run each attempt with the
    same options by construction: ``exact``, ``long-horizon`` and ``sampling-*`` keep
    the interior-point solver's acceptable stop in C as in Python (flagged ``optimal_inaccurate`` by
    ``<P>_inaccurate``), where the C used to switch it off (session 14)."""
    stop = EMITTED_STOP_OPTIONS.get(plugin, {})
    verdict = {k: v for k, v in STATUS_OPTIONS.get(plugin, {}).items() if k not in stop}
    return {**opts, **verdict}


class _Problem:
    """The C pieces of one compiled problem under the C prefix ``P``."""

    def __init__(self, c: CasadiCompiled, P: str, title: str, module: str,
                 accept_tol: float | None = None, allow_external: bool | None = None,
                 staged_ok: bool = False):
        #: for a problem compiled in stage order (the structured targets, issue #14 §2):
        #: ``take[i]`` = the position of layout element ``i`` in the solver's vector
        self.take = _staged_take(c, title, staged_ok)
        self.c, self.P, self.title, self.module = c, P, title, module
        self.nw = int(c.nlp["x"].numel())
        self.np = int(c.nlp["p"].numel())
        self.ng = int(c.nlp["g"].numel())
        self.tol_pr = float(c.options.get("tol_pr", 1e-6))
        self.tol_du = float(c.options.get("tol_du", 1e-6))
        self.accept_tol = STALL_TOL if accept_tol is None else float(accept_tol)
        self.solvers = [(f"{P}_nlp", c.solver_name, dict(c.options))]
        #: per attempt: 1 when its C returns the solver's own verdict (STATUS_OPTIONS: the
        #: interior-point last resort), which bal/problem.c uses in place of the KKT test
        self.reports = [int(c.solver_name in STATUS_OPTIONS)]
        # the cold-start retries the emitted C runs (backends.emittable.c_retries): the
        # same solver again reuses its function, other settings get their own
        self.retry_labels, self.retry_docs = [], []
        # an iteration budget (real-time mode): a stop by it is BAL_TRUNCATED, and no retry
        # runs after any failure (the budgeted targets have none: the time bound)
        budget = getattr(c, "budget", None)
        self.budget = 0 if budget is None or budget.iterations is None else \
            int(budget.iterations)
        # (the emittable entries of the compiled problem's own chain; retries that link a
        # library only with allow_external, by default when the first attempt links one —
        # the rule of runtime.mirror_c_retries, so a mirrored Python runs the C's chain)
        if allow_external is None:
            allow_external = retries_link_libraries(c.solver_name, c.options)
        attempts = [] if self.budget else c_retries(c.solver_name, c.options, c.retries,
                                                    allow_external)
        #: libraries the retries' C links (the first attempt's: ``c.target.c_libraries()``)
        self.libraries = tuple(lib for plugin, _, opts, _ in attempts
                               for lib in c_libraries(plugin, opts))
        for k, (plugin, over, opts, label) in enumerate(attempts):
            sym = f"{P}_nlp" if plugin == c.solver_name and not over else \
                f"{P}_nlp_retry{k + 1}"
            if plugin != c.solver_name:  # the options Python builds this retry with
                opts = c._retry_options(plugin, over)
            self.solvers.append((sym, plugin, opts))
            self.reports.append(int(plugin in STATUS_OPTIONS))
            self.retry_labels.append(label)
            self.retry_docs.append(" ".join([plugin, *(f"{o} {v!r}" for o, v in over.items())])
                                   if over else f"{plugin} again, cold (skipped after a cold "
                                   "first attempt: the same run)" if plugin == c.solver_name
                                   else f"{plugin} (cold start)")
        #: the attempt whose solver runs from a second start (``P_solve_from``; the
        #: ``second_solver`` of :meth:`CasadiCompiled.solve`): 0, the first solver, unless
        #: :meth:`set_second_solver` says otherwise
        self.second_solver = 0
        #: per attempt of the compiled problem's chain (0 the first solver, ``k`` its
        #: ``k``-th retry), the index of the C attempt running it, ``None`` for a retry the
        #: C leaves out (the emitted retries are the chain's emittable ones, in order;
        #: equal entries are kept or left out alike, so matching in order is exact)
        self.c_attempt: list[int | None] = [0]
        j = 0  # the emitted retries matched so far
        for name, over in c.retries:
            hit = j < len(attempts) and attempts[j][:2] == (name, dict(over))
            j += hit
            self.c_attempt.append(j if hit else None)
        self.layout = c.layout  # the solver's x: the user's variables, then epigraph blocks
        self.vars = self.layout.to_dict()
        self.params = c.ocp.parameter_layout.to_dict()  # with declared values as "default"
        init = self.layout.initial()
        self.init = np.where(np.isfinite(init), init, 0.0)
        if self.take is not None:  # the cold start in the solver's (stage) order
            staged = np.empty_like(self.init)
            staged[self.take] = self.init
            self.init = staged

    def set_second_solver(self, which: int) -> None:
        """Run the solver of attempt ``which`` (``CasadiCompiled.solve(second_solver=)``: 0
        the first, ``k`` the ``k``-th retry's, -1 the last) from a second start. The index
        names an attempt of the compiled problem's own chain (Python's): the C runs the
        same solver (:attr:`c_attempt`, its index in the C chain when the C leaves out
        retries, e.g. ``fast-sqp``'s last, which links a library); refused when the C
        leaves that retry out."""
        k = chain_solver_index(which, len(self.c.retries))
        j = self.c_attempt[k]
        if j is None:
            name = self.c.retries[k - 1][0]
            raise CodegenError(f"{self.P}: second_solver {which} names retry {k} ({name}), "
                               f"whose C is not emitted (the C runs "
                               f"{len(self.solvers) - 1} of the {len(self.c.retries)} "
                               f"retries); choose an emitted attempt (0: the first solver)")
        self.second_solver = j

    def nlpsol_options(self) -> list[tuple[str, str, dict]]:
        """Per attempt ``(symbol, plugin, nlpsol options)`` of the generated solvers (without
        the shared derivative functions): :func:`c_solver_options` of the options Python
        runs that attempt with."""
        return [(sym, plugin, c_solver_options(plugin, opts))
                for sym, plugin, opts in self.solvers]

    def functions(self) -> dict[str, ca.Function]:
        # every attempt on the compiled problem's own plugin shares its derivative
        # functions, so their C is generated once (backends.casadi_backend.
        # shared_derivatives: most of the C of a nonlinear horizon problem), built on the
        # compact lowering (EMIT_LOWERING: the dynamics' derivatives once, not per stage)
        # (a stage-ordered problem keeps its own, expanded NLP: the structure options
        # describe that vector; its declared cost at the layout's point is P_obj)
        c = self.c
        if self.take is not None:  # stage order: the compact lowering permuted, per plugin
            # (EMIT_LOWERING "expanded": the solver's own NLP, each solver deriving its own
            # functions — on the cart-pole pair 6x the C, 11-15x the build time, a 20 %
            # faster step; docs/engines.md)
            if EMIT_LOWERING == "compact":
                nlp, caches = c.staged_compact()
                if c.solver_name not in caches:
                    raise CodegenError(f"{self.title}: the stage-ordered solver "
                                       f"{c.solver_name!r} has no compact derivatives to "
                                       f"emit (those exist for {sorted(caches)})")
                jac_fg = _staged_jac_fg(caches[c.solver_name])
            else:
                nlp, caches, jac_fg = c.nlp, {}, {}
            out = {sym: ca.nlpsol(sym, plugin, nlp, {**opts, "cache": caches.get(plugin, {})})
                   for sym, plugin, opts in self.nlpsol_options()}
            out[f"{self.P}_kkt"] = _kkt_function(c, f"{self.P}_kkt", lowered=(nlp, jac_fg))
            out[f"{self.P}_obj"] = c.inverse.cost
            return out
        nlp, derivatives = c.lowered(EMIT_LOWERING)
        out = {sym: ca.nlpsol(sym, plugin, nlp, c.with_derivatives(opts, derivatives)
                              if plugin == c.solver_name else opts)
               for sym, plugin, opts in self.nlpsol_options()}
        out[f"{self.P}_kkt"] = _kkt_function(self.c, f"{self.P}_kkt", EMIT_LOWERING)
        return out

    def config(self, cfg: C.Config) -> None:
        """The ``#define``\\ s of this problem for ``<name>_config.h`` (read by
        ``bal/problem.h`` and ``bal/problem.c`` under the prefix ``P``)."""
        P, syms = self.P, [sym for sym, _, _ in self.solvers]
        pdoc = "".join(f"\n  {n}: offset {v['offset']}, shape {tuple(v['shape'])}"
                       for n, v in self.params.items()) or " none"
        vdoc = "".join(f"\n  {n}: offset {v['offset']}, shape {tuple(v['shape'])}"
                       for n, v in self.vars.items())
        n_user = self.layout.user_size
        if self.nw > n_user:
            vdoc += (f"\n  (epigraph variables of non-smooth costs: offset {n_user}"
                     f", {self.nw - n_user} values)")
        retries = "; ".join(self.retry_docs) or "none"
        cfg.comment(
            f"---- problem {P}: {self.title} (bal/problem.h) ----\n"
            f"Parameters p (stacked, {self.np} values):{pdoc}\n"
            f"Decision vector x ({self.nw} values):{vdoc}\n"
            f"Constraint rows: {self.ng}. BAL_OK when max violation < {self.tol_pr:g} and "
            f"inf-norm of the\nLagrangian gradient < {self.tol_du:g} (the solver's own tests; "
            "an attempt with P_REPORTS 1\nby its solver's own verdict). An attempt that did not"
            "\nconverge is retried from a cold start with, in order: "
            f"{retries}.\nIf none converges, BAL_FEASIBLE with the last attempt whose violation "
            f"scaled by 1 + |g|\nis <= {self.accept_tol:g} (its point, value and multipliers in "
            "the work struct), as balustrade's backend.")
        cfg.define(f"{P}_NP", self.np)
        cfg.define(f"{P}_NW", self.nw)
        cfg.define(f"{P}_NG", self.ng)
        cfg.define(f"{P}_NG1", max(self.ng, 1), "rows of the bound arrays")
        cfg.define(f"{P}_N_USER", self.layout.user_size, "declared variables (no epigraph)")
        cfg.define(f"{P}_N_SOLVERS", len(syms), "first attempt + retries")
        cfg.xmacro(f"{P}_SOLVERS", syms)
        cfg.define(f"{P}_REPORTS", "{" + ", ".join(map(str, self.reports)) + "}",
                   "per attempt: 1 if its solver returns its own verdict (0: converged)")
        # the acceptable stop of a solver that reports it (emittable.ACCEPTABLE_STOP: the
        # interior-point solver's): its return status accessor and that status' value
        stops = [ACCEPTABLE_STOP.get(plugin) for _, plugin, _ in self.solvers]
        cfg.define(f"{P}_RETURN_STATUS_FNS", "{" + ", ".join(
            f"{sym}{RETURN_STATUS_SUFFIX}" if stop is not None else "0"
            for (sym, _, _), stop in zip(self.solvers, stops)) + "}",
                   "per attempt: its solver's own return status accessor (0: none)")
        cfg.define(f"{P}_ACCEPTABLE_STOP", "{" + ", ".join(
            str(-1 if stop is None else stop) for stop in stops) + "}",
                   "per attempt: the return status of a stop at the acceptable level "
                   "(BAL_OK, P_inaccurate 1)")
        uniq = list(dict.fromkeys(syms))
        for key in ("ARG", "RES", "IW", "W"):
            expr = f"{uniq[0]}_SZ_{key}"
            for sym in uniq[1:]:
                expr = f"BAL_MAX2({expr}, {sym}_SZ_{key})"
            cfg.define(f"{P}_SZ_{key}", expr)
        cfg.define(f"{P}_TOL_PR", C.c_double(self.tol_pr))
        cfg.define(f"{P}_TOL_DU", C.c_double(self.tol_du))
        cfg.define(f"{P}_F_SCALE", C.c_double(getattr(self.c, "objective_scale", 1.0)),
                   "the solver's objective is the declared one times this")
        cfg.define(f"{P}_ACCEPT_TOL", C.c_double(self.accept_tol))
        cfg.define(f"{P}_SECOND_SOLVER", self.second_solver,
                   "the attempt whose solver runs from a second start (P_solve_from)")
        cfg.define(f"{P}_BUDGET", self.budget,
                   "iteration budget (0: none); a stop by it is BAL_TRUNCATED")
        cfg.define(f"{P}_TRUNC_TOL", C.c_double(FEASIBILITY_TOL),
                   "a BAL_TRUNCATED iterate with primal residual <= this is feasible")
        for n, v in self.params.items():
            cfg.define(f"{P}_P_{n}", v["offset"])
        for n, v in self.vars.items():
            cfg.define(f"{P}_W_{n}", v["offset"])
        cfg.array(f"{P}_LBX", self.c.lbx, self.nw)
        cfg.array(f"{P}_UBX", self.c.ubx, self.nw)
        cfg.array(f"{P}_LBG", self.c.lbg, 1)
        cfg.array(f"{P}_UBG", self.c.ubg, 1)
        cfg.array(f"{P}_INIT_X", self.init, self.nw)
        cfg.define(f"{P}_STAGED", int(self.take is not None),
                   "1: x is in stage order (P_TAKE), the offsets P_W_* are the layout's")
        if self.take is not None:
            lb, ub = self.c._layout_bounds
            cfg.comment("layout element i of the solution is x[P_TAKE[i]], projected onto "
                        "[P_LBX_L[i], P_UBX_L[i]]\n(the backend's StageInverse.primal, "
                        "then its projection onto the bounds)")
            cfg._braced(f"{P}_TAKE", [", ".join(map(str, self.take[k: k + 12]))
                                      for k in range(0, self.nw, 12)])
            cfg.array(f"{P}_LBX_L", lb, self.nw)
            cfg.array(f"{P}_UBX_L", ub, self.nw)
        cfg.blank()

    def manifest(self) -> dict:
        return {"prefix": self.P, "title": self.title, "np": self.np, "nw": self.nw,
                "ng": self.ng, "n_user": self.layout.user_size, "variables": self.vars,
                "parameters": self.params, "tol_pr": self.tol_pr, "tol_du": self.tol_du,
                "accept_tol": self.accept_tol, "budget": self.budget,
                "acceptable_stop": any(plugin in ACCEPTABLE_STOP
                                       for _, plugin, _ in self.solvers),
                "retries": list(self.retry_labels),
                "solver": self.c.solver_name, "qpsol": self.c.options.get("qpsol"),
                **({} if self.take is None else {
                    "take": self.take.tolist(),
                    "lbx_layout": list(map(float, self.c._layout_bounds[0])),
                    "ubx_layout": list(map(float, self.c._layout_bounds[1]))})}


def _staged_jac_fg(fns: dict[str, ca.Function]) -> dict[str, ca.Function]:
    """``{"jac_fg": (x, p) -> (f, ∇f, g, ∂g/∂x)}`` from the staged compact functions of the
    first attempt's solver (the KKT check then reuses their C)."""
    x, p = fns["nlp_jac_g"].mx_in()
    g, jac_g = fns["nlp_jac_g"](x, p)
    jac_fg = ca.Function("nlp_jac_fg", [x, p], [fns["nlp_f"](x, p), fns["nlp_grad_f"](x, p),
                                                g, jac_g],
                         ["x", "p"], ["f", "grad_f_x", "g", "jac_g_x"])
    return {"jac_fg": jac_fg}


def _staged_take(c: CasadiCompiled, title: str, staged_ok: bool) -> np.ndarray | None:
    """``None`` for a problem in the layout's order; for one compiled in stage order
    (:mod:`~balustrade.backends.passes.stage_order`) the positions ``take`` of the layout's
    elements in the solver's vector, when the emitter maps them (``staged_ok``, the PCBF
    step) and the stage order is a permutation (no lifted copies or running sums: a warm
    start is then a scatter, as the backend's ``StageInverse.staged``); else a
    CodegenError saying why."""
    stages = getattr(c, "stages", None)
    if stages is None:
        return None
    if not staged_ok:
        raise CodegenError(f"{title}: problems compiled in stage order (the structured "
                           "targets) are emitted only inside the PCBF step (emit_pcbf), which "
                           "maps the stage order; this emitter unpacks the layout order")
    take = np.asarray(stages.take, dtype=int)
    n = int(c.nlp["x"].numel())
    rows = np.asarray(stages.row_take, dtype=int)
    if take.size != n or not np.array_equal(np.sort(take), np.arange(n)) \
            or rows.size != int(c.nlp["g"].numel()):
        raise CodegenError(f"{title}: its stage order lifts variables (per-stage copies or "
                           f"running sums: {n} staged values for {take.size} layout "
                           "values); the emitted step maps only a stage order that permutes "
                           "the layout")
    return take


def _write_module(name: str, out_dir: Path, what: str, config: C.Config,
                  parts: list[tuple[str, str]], casadi_files: list[Path], manifest: dict,
                  libs: tuple[str, ...]) -> Emitted:
    """Write the static C (``bal/``), ``<name>_config.h`` (``config``), the glue
    ``<name>.h``/``<name>.c`` instantiating ``parts`` (``(kind, prefix)``) and
    ``<name>.json``."""
    static = C.copy_static(out_dir)
    cfg = out_dir / f"{name}_config.h"
    h = out_dir / f"{name}.h"
    c = out_dir / f"{name}.c"
    cfg.write_text(C.config_header(name, what, config))
    h.write_text(C.glue_header(name, what, parts))
    c.write_text(C.glue_source(name, parts))
    manifest = {"version": MANIFEST_VERSION, "name": name, "casadi": ca.__version__,
                "libraries": list(libs), **manifest,
                "status_codes": S.manifest(S.SOLVE)}
    (out_dir / f"{name}.json").write_text(json.dumps(manifest, indent=1))
    return Emitted(name, out_dir, [c, casadi_files[0]], [h, cfg, casadi_files[1]], manifest,
                   libs, static)


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
    cfg = C.Config()
    cfg.comment(f"Plain functions: see the CasADi entry points declared in {name}_casadi.h: "
                f"{', '.join(functions)}")
    return _write_module(name, out_dir, "plain CasADi functions", cfg, [], files,
                         {"kind": "functions", "functions": info}, ())


def emit_function(fn: ca.Function, name: str, out_dir: str | Path) -> Emitted:
    """:func:`emit_functions` for one function, emitted under the C symbol ``name``."""
    return emit_functions({name: fn}, name, out_dir)


def emit_problem(compiled: CasadiCompiled, name: str, out_dir: str | Path,
                 allow_external: bool = False, accept_tol: float | None = None) -> Emitted:
    """Emit one compiled problem (e.g. the slack problem (2.24)) under the C prefix
    ``<name>_p`` (``bal/problem.h``), with the entry point
    ``int <name>_p_solve(<name>_p_work* wk, const casadi_real* p)``: parameters ``p``
    stacked in declaration order (``<name>_p_NP`` values; ``<name>_p_P_x0`` is the offset
    of ``x0``), warm start in ``wk->x0/lam_x0/lam_g0``, outputs ``wk->x`` (full primal
    solution; ``<name>_p_W_u`` is the offset of ``u``, so ``u_{0|k}`` is
    ``wk->x[<name>_p_W_u]``), ``wk->f`` (value), return value = status (``BAL_*``).
    Also ``<name>_p_init``/``_finalize``/``_alloc``/``_free``, ``<name>_p_cold_start``,
    ``<name>_p_warm_start``, ``<name>_p_warm_start_primal``, ``<name>_p_primal``,
    ``<name>_p_value``, ``<name>_p_residuals`` (all listed in ``<name>.h``).

    ``BAL_OK`` uses the solver's own tolerances ``tol_pr``/``tol_du``. Attempts that do not
    converge are retried from a cold start with the retries of the target that emitted C
    runs (:func:`~balustrade.backends.emittable.c_retry_chain`: the compiled problem's chain
    without the entries needing an external library, such as the interior-point last resort
    of the fast-sqp target, unless the first attempt links one itself — the rule of
    :func:`~balustrade.codegen.mirror_c_retries`). If
    none converges and the last attempt's scaled constraint violation is ``<= accept_tol``
    (default ``1e-8``) the status is ``BAL_FEASIBLE``: safe to apply, possibly suboptimal."""
    _check_identifier(name)
    _check_accept_tol(name, accept_tol)
    libs = _check_compiled(compiled, name, allow_external)
    out_dir = _out_dir(out_dir, name)
    prob = _Problem(compiled, name + "_p", compiled.ocp.name, name, accept_tol)
    files = _generate(prob.functions(), name, out_dir)
    cfg = C.Config()
    prob.config(cfg)
    return _write_module(name, out_dir, f"the problem {compiled.ocp.name!r}", cfg,
                         [("problem", prob.P)], files,
                         {"kind": "problem", "problems": {"problem": prob.manifest()}}, libs)


def emit_problems(problems: object, name: str, out_dir: str | Path,
                  allow_external: bool = False, accept_tol: float | None = None) -> Emitted:
    """Emit several compiled problems into one module: those of a controller whose step has
    no emitted C (its :class:`~balustrade.control.deploy.ProblemsDeployment`, e.g.
    Algorithm 5.2's (5.15) and (5.16)), the spec itself, or a dict ``{key: compiled}``.
    Each problem gets the prefix ``<name>_<key>`` and the entry points of
    :func:`emit_problem` (``<name>_<key>_solve``, ...); ``CProblem(lib, problem=key)``
    calls one from Python."""
    _check_identifier(name)
    _check_accept_tol(name, accept_tol)
    if isinstance(problems, dict):
        spec = ProblemsDeployment(dict(problems), f"the problems of {name}")
    else:
        spec = _spec(problems, name, ProblemsDeployment,
                     "controller with compiled problems (or a dict key -> compiled problem)")
    if not spec.problems:
        raise CodegenError(f"{name}: no problems to emit")
    libs: tuple[str, ...] = ()
    for key, compiled in spec.problems.items():
        _check_identifier(key, f"{name}: problem key")
        libs += _check_compiled(compiled, f"{name}: problem {key!r}", allow_external)
    out_dir = _out_dir(out_dir, name)
    probs = {key: _Problem(c, f"{name}_{key}", f"{key} {c.ocp.name!r} of {spec.algorithm}",
                           name, accept_tol) for key, c in spec.problems.items()}
    functions: dict[str, ca.Function] = {}
    for prob in probs.values():
        functions.update(prob.functions())
    files = _generate(functions, name, out_dir)
    cfg = C.Config()
    for prob in probs.values():
        prob.config(cfg)
    return _write_module(name, out_dir, spec.algorithm, cfg,
                         [("problem", prob.P) for prob in probs.values()], files,
                         {"kind": "problems",
                          "problems": {key: prob.manifest() for key, prob in probs.items()}},
                         tuple(sorted(set(libs))))


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

    The controller's shifted-plan certificate (:mod:`balustrade.control.shifted`; on by
    default) is emitted as ``<name>_shift_cert`` (its
    :meth:`~balustrade.control.shifted.ShiftedCertificate.function`) and checked by the
    step as the Python filter checks it; ``manifest["shifted_certificate"]`` says whether
    it was emitted (not for a controller built with ``shifted_certificate=False``).
    With ``certificate_first`` (the controller's or the spec's; on by default wherever the
    certificate is emitted) the step checks it before (2.24) and skips the solve when it
    certifies ``h_PB = 0`` (``<name>_CERT_FIRST``, ``manifest["certificate_first"]``), as
    the Python filter does; without the certificate it is off. With ``shifted_retry``
    (the controller's option, off by default; ``<name>_SHIFTED_RETRY``,
    ``manifest["shifted_retry"]``) a certified step's failed (2.23) attempt from its last
    solution is tried once more from the shifted plan before the cold retries, by the
    solver of the attempt ``shifted_retry_solver`` names (``<name>_filter_SECOND_SOLVER``,
    ``manifest["shifted_retry_solver"]``, the resolved attempt index; 0 the first solver).
    """
    _check_identifier(name)
    _check_accept_tol(name, accept_tol)
    _check_dynamics(name, dynamics)
    out_dir = _out_dir(out_dir, name)
    spec = _spec(controller, name, PCBFDeployment, "PCBFSafetyFilter")
    slack, filt, U, libs = _controller_pair(
        name, spec.slack, spec.filter, spec.U,
        ("slack problem (2.24)", "filter problem (2.23)"), allow_external)
    s = _Problem(slack, f"{name}_slack", f"slack problem (2.24) {slack.ocp.name!r}", name,
                 accept_tol, staged_ok=True)
    f = _Problem(filt, f"{name}_filter", f"filter problem (2.23) {filt.ocp.name!r}", name,
                 accept_tol, staged_ok=True)
    libs += s.libraries + f.libraries
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
    shared = [f"{s.vars[vn]['offset']}, {lay['offset']}, {int(np.prod(lay['shape']))}"
              for vn, lay in f.vars.items()
              if vn in s.vars and s.vars[vn]["shape"] == lay["shape"]]
    functions = {**s.functions(), **f.functions()}
    cert = _shift_certificate(controller, spec, name)
    if cert is not None:
        functions[f"{name}_shift_cert"] = cert.function(f"{name}_shift_cert")
    if dynamics is not None:
        functions[f"{name}_dynamics"] = dynamics
    files = _generate(functions, name, out_dir)
    first = bool(spec.certificate_first) and cert is not None
    retry = bool(spec.shifted_retry) and first
    if retry:  # before f.config: its P_SECOND_SOLVER
        f.set_second_solver(int(spec.shifted_retry_solver))
    cfg = C.Config()
    s.config(cfg)
    f.config(cfg)
    cfg.comment(f"---- the PCBF control step {name}: (2.24) then (2.23) (bal/pcbf.h) ----")
    cfg.define(f"{name}_SHIFT_CERT", int(cert is not None),
               "the shifted-plan certificate of h_PB = 0 (balustrade.control.shifted)")
    cfg.define(f"{name}_CERT_FIRST", int(first),
               "certificate first: skip (2.24) when the shifted plan certifies h_PB = 0")
    cfg.define(f"{name}_SHIFTED_RETRY", int(retry),
               "a certified step's failed (2.23) is tried from the shifted plan first")
    cfg.define(f"{name}_EPS", C.c_double(spec.eps), "the relaxation eps of (2.23)")
    cfg.define(f"{name}_CERT_TOL", C.c_double(cert.tol if cert is not None
                                               else FEASIBILITY_TOL),
               "largest violation of (2.24) by a certified shifted plan")
    cfg.define(f"{name}_NX", nx)
    cfg.define(f"{name}_NU", nu)
    cfg.define(f"{name}_N", N)
    cfg.define(f"{name}_N_XI", int(np.prod(s.vars["xi"]["shape"])), "slacks xi of (2.24)")
    cfg.define(f"{name}_ZERO_TOL", C.c_double(spec.zero_tol),
               "a feasible (2.24) of cost <= this is optimal")
    cfg.array(f"{name}_U_LB", U.lb)
    cfg.array(f"{name}_U_UB", U.ub)
    cfg.comment("variables of (2.23) shared with (2.24): X(offset in (2.24), offset in (2.23), "
                "size)")
    cfg.xmacro(f"{name}_SHARED", shared)
    cfg.status(S.PCBF, "BAL_PCBF_STATUS_CODES")
    manifest = {"kind": "pcbf", "nx": nx, "nu": nu, "N": N, "eps": float(spec.eps),
                "U": {"lb": list(map(float, U.lb)), "ub": list(map(float, U.ub))},
                "problems": {"slack": s.manifest(), "filter": f.manifest()},
                "dynamics": dynamics is not None,
                "shifted_certificate": cert is not None,
                "certificate_first": first,
                "shifted_retry": retry,
                "shifted_retry_solver": f.second_solver,
                "pcbf_status": S.manifest(S.PCBF),
                # the solver libraries of the casadi wheel the C links (the structured
                # target's): the flags accelerate() and build() need
                "link_flags": list(_link_flags(tuple(sorted(set(libs)))))}
    return _write_module(name, out_dir, "the PCBF safety filter (2.24)+(2.23)", cfg,
                         [("problem", s.P), ("problem", f.P), ("pcbf", name)], files,
                         manifest, tuple(sorted(set(libs))))


def _link_flags(libs: tuple[str, ...]) -> tuple[str, ...]:
    """:func:`~balustrade.codegen.emit_rapsf.link_flags`, plus the include folders the
    libraries' generated C needs (:func:`~balustrade.backends.emittable.include_subdirs`)."""
    from balustrade.codegen.emit_rapsf import casadi_dir, link_flags

    extra = tuple(f"-I{casadi_dir() / 'include' / d}" for d in include_subdirs(libs))
    return (*extra, *link_flags(libs))


def _shift_certificate(controller: object, spec: PCBFDeployment, name: str
                       ) -> ShiftedCertificate | None:
    """The shifted-plan certificate the emitted step evaluates: the controller's own
    (``None`` when it was built with ``shifted_certificate=False``), or for a bare
    :class:`PCBFDeployment` the one its ``shifted_certificate`` field asks for; ``None`` if
    the slack problem does not admit one (:attr:`ShiftedCertificate.available`)."""
    if hasattr(controller, "certificate"):
        cert = controller.certificate
    elif spec.shifted_certificate:
        cert = ShiftedCertificate(spec.slack, spec.zero_tol)
    else:
        cert = None
    if cert is None or not cert.available:
        return None
    n_user, n_w = spec.slack.layout.user_size, cert.function(f"{name}_shift_cert").numel_out(0)
    if n_w != n_user:
        raise CodegenError(f"{name}: the shifted-plan candidate has {n_w} values, (2.24) "
                           f"{n_user} declared variables")
    return cert


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
    (emitted.out_dir / "example.h").write_text(
        C.example_header(emitted.name, len(x_init), int(steps), x_init, u_p))
    main_path = emitted.out_dir / "main.c"
    main_path.write_text(C.static_text("example_main.c"))
    mk = emitted.out_dir / "Makefile"
    mk.write_text(C.makefile(emitted.name))
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
    emitted as ``<name>_h`` and ``<name>_h_next``; ``U`` must be a Box. A controller built
    with ``network=`` (the MLP ``ĥ`` came from) has the step evaluate ``ĥ`` from the weights
    instead (``bal/approx_net.c``, the model as ``<name>_f``): the same operations in the
    same order, compact code (the CasADi functions stay in the library, unused by the
    step). The solvers of (7.6) and (7.5) keep CasADi's code either way."""
    _check_identifier(name)
    _check_accept_tol(name, accept_tol)
    _check_dynamics(name, dynamics)
    out_dir = _out_dir(out_dir, name)
    spec = _spec(controller, name, ApproximateDeployment, "ApproximatePCBFFilter")
    dec, filt, U, libs = _controller_pair(
        name, spec.decrease, spec.filter, spec.U,
        ("maximal decrease problem (7.6)", "filter problem (7.5)"), allow_external)
    system = spec.system
    d = _Problem(dec, f"{name}_dec", f"maximal decrease (7.6) {dec.ocp.name!r}", name,
                 accept_tol)
    f = _Problem(filt, f"{name}_filter", f"filter (7.5) {filt.ocp.name!r}", name, accept_tol)
    _require(name, {"(7.6) parameter": (d.params, ["x0"]), "(7.6) variable": (d.vars, ["u"]),
                    "(7.5) parameter": (f.params, ["x0", "u_p", "dh", "rho"]),
                    "(7.5) variable": (f.vars, ["u"])},
             "build the problems with balustrade.problems.approximate")
    grid = np.atleast_2d(np.asarray(spec.grid, dtype=float))
    x, u = ca.SX.sym("x", system.nx), ca.SX.sym("u", system.nu)
    h = spec.h
    functions = {**d.functions(), **f.functions(),
                 f"{name}_h": ca.Function(f"{name}_h", [x], [h(x)], ["x"], ["h"]),
                 f"{name}_h_next": ca.Function(f"{name}_h_next", [x, u], [h(system(x, u))],
                                               ["x", "u"], ["h_next"])}
    for key in (f"{name}_h", f"{name}_h_next"):  # the C reads one double: more overruns it
        if functions[key].numel_out(0) != 1:
            raise CodegenError(f"{name}: ĥ must be scalar, {key} has an output of shape "
                               f"{functions[key].size_out(0)}")
    if dynamics is not None:
        functions[f"{name}_dynamics"] = dynamics
    net = spec.network
    if net is not None:  # ĥ from the network's weights (bal/approx_net.c): f alone from CasADi
        functions[f"{name}_f"] = ca.Function(f"{name}_f", [x, u], [system(x, u)],
                                             ["x", "u"], ["x_next"])
    files = _generate(functions, name, out_dir)
    nc = len(grid) + 2
    cfg = C.Config()
    d.config(cfg)
    f.config(cfg)
    cfg.comment(f"---- Algorithm 7.5, the approximate PCBF filter {name} (bal/approx.h) ----")
    cfg.define(f"{name}_NX", system.nx)
    cfg.define(f"{name}_NU", system.nu)
    cfg.define(f"{name}_NC", nc, "screened candidates: clip(0), clip(u_p), the grid")
    cfg.define(f"{name}_N_LOCAL", int(spec.n_local), "local (7.6) solves")
    cfg.define(f"{name}_RHO", C.c_double(spec.rho))
    cfg.define(f"{name}_CERTIFY", int(bool(spec.certify)), "line 4 (initial value)")
    cfg.define(f"{name}_EXACT_SHORTCUT", int(bool(spec.exact_shortcut)))
    _network_config(cfg, name, net, functions[f"{name}_h"], system.nx)
    cfg.array(f"{name}_U_LB", U.lb)
    cfg.array(f"{name}_U_UB", U.ub)
    cfg.matrix(f"{name}_GRID", grid)
    cfg.status(S.APPROX, "BAL_APPROX_STATUS_CODES")
    manifest = {"kind": "approximate", "nx": system.nx, "nu": system.nu, "n_candidates": nc,
                "n_local": int(spec.n_local), "rho": float(spec.rho),
                "certify": bool(spec.certify),
                "U": {"lb": list(map(float, U.lb)), "ub": list(map(float, U.ub))},
                "problems": {"dec": d.manifest(), "filter": f.manifest()},
                "dynamics": dynamics is not None,
                "exact_shortcut": bool(spec.exact_shortcut),
                "network": net is not None,
                "approx_status": S.manifest(S.APPROX)}
    return _write_module(name, out_dir, "Algorithm 7.5, the approximate PCBF filter "
                         "(7.5)+(7.6)", cfg,
                         [("problem", d.P), ("problem", f.P), ("approx", name)], files,
                         manifest, tuple(sorted(set(libs))))


def _network_forward(net: object, X: np.ndarray) -> np.ndarray:
    """What bal/approx_net.c computes, in numpy, on the rows of ``X`` (softplus above
    ``net.softplus_threshold``: linear, as the network's own forward pass)."""
    z = (np.atleast_2d(X) - np.asarray(net.mean, float)) / np.asarray(net.scale, float)
    n, t = len(net.weights), _softplus_threshold(net)
    for k, (W, b) in enumerate(zip(net.weights, net.biases)):
        z = z @ np.asarray(W, float).T + np.asarray(b, float).reshape(-1)
        if k < n - 1:
            z = np.where(z > t, z, np.log1p(np.exp(np.minimum(z, t))))
    return z[:, 0] ** 3 if net.output_transform == "cbrt" else z[:, 0]


def _softplus_threshold(net: object) -> float:
    """The network's softplus threshold (``MLPModel.softplus_threshold``, from
    ``balustrade.learn.train.SOFTPLUS_THRESHOLD``); a CodegenError if it has none."""
    t = getattr(net, "softplus_threshold", None)
    if not isinstance(t, (int, float)) or not np.isfinite(t):
        raise CodegenError(f"the network ({type(net).__name__}) has no finite "
                           f"softplus_threshold (balustrade.learn.train.MLPModel has one), "
                           f"got {t!r}")
    return float(t)


def _network_config(cfg: C.Config, name: str, net: object | None, h: ca.Function,
                    nx: int) -> None:
    """``<name>_NET`` and, for a network, its layers for bal/approx_net.c; a network whose
    shapes do not chain, or that does not compute ``ĥ`` (relative 1e-9 on a few states),
    raises a CodegenError naming it."""
    cfg.define(f"{name}_NET", int(net is not None), "h^ from the network's weights")
    if net is None:
        return
    W = [np.asarray(w, float) for w in net.weights]
    b = [np.asarray(v, float).reshape(-1) for v in net.biases]
    sizes = [nx] + [w.shape[0] if w.ndim == 2 else -1 for w in W]
    ok = (len(W) == len(b) and sizes[-1] == 1 and net.output_transform in (None, "cbrt")
          and np.shape(net.mean) == (nx,) and np.shape(net.scale) == (nx,)
          and all(w.shape == (sizes[k + 1], sizes[k]) and len(v) == sizes[k + 1]
                  for k, (w, v) in enumerate(zip(W, b))))
    if not ok:
        raise CodegenError(f"{name}: the network's layers do not chain from {nx} states to "
                           f"one value (weights {[w.shape for w in W]}, biases "
                           f"{[v.shape for v in b]}, output_transform "
                           f"{net.output_transform!r})")
    X = np.random.default_rng(2).uniform(-1.0, 1.0, (4, nx))
    want = np.array([float(h(x)) for x in X])
    got = _network_forward(net, X)
    if not np.allclose(got, want, rtol=1e-9, atol=1e-12):
        raise CodegenError(f"{name}: the network does not compute h^ (softplus layers, "
                           f"threshold {_softplus_threshold(net):g}): {got} where h^ gives "
                           f"{want} on 4 test states")
    cfg.define(f"{name}_NET_NL", len(W), "layers")
    cfg.define(f"{name}_NET_SIZES", "{" + ", ".join(map(str, sizes)) + "}", "widths")
    cfg.define(f"{name}_NET_MAXW", max(sizes))
    cfg.define(f"{name}_NET_CUBE", int(net.output_transform == "cbrt"), "h^ = output cubed")
    cfg.define(f"{name}_NET_THRESHOLD", C.c_double(_softplus_threshold(net)),
               "softplus: linear above this input")
    cfg.array(f"{name}_NET_W", np.concatenate([w.reshape(-1) for w in W]))
    cfg.array(f"{name}_NET_B", np.concatenate(b))
    cfg.array(f"{name}_NET_MEAN", np.asarray(net.mean, float))
    cfg.array(f"{name}_NET_SCALE", np.asarray(net.scale, float))
