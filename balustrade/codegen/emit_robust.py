"""Emit Algorithm 5.2, the robust PCBF safety filter (5.15)+(5.16), and Algorithm 6.4, the
multiobjective robust PCBF controller ((5.15) once, then (6.15)), as one C call per step.

:func:`emit_robust` writes the module of :mod:`~balustrade.codegen.emit` (``bal/``,
``<name>_config.h``, ``<name>.h/.c``, ``<name>_casadi.c/.h``, ``<name>.json``) with the
step ``<name>_step(x, u_p, u_out, h_out, status, work)`` of ``bal/robust.c``: the decisions
and fallbacks of :class:`~balustrade.control.robust.RobustPCBFSafetyFilter`, the numbers
between the solves as two emitted CasADi functions:

* ``<name>_post(w, f)`` — the polished slacks of (5.15) (:func:`~balustrade.control.
  robust_steps.polished_slacks`: elementwise minimum of the solver's slacks, clipped at 0,
  and the slacks its ``z`` needs) and ``h_r = h̃(ξ)`` of the polished slacks (SPEC §1.12);
* ``<name>_cand(z, v, ξ)`` — the shifted candidate (5.17)
  (:func:`~balustrade.control.robust_steps.robust_candidate`) with ``h̃`` of it.

``π_f`` must be an expression (:class:`~balustrade.dsl.policies.AffinePolicy`, a
``casadi.Function``): the C evaluates it as Python's tube functions do, and a numpy-only
``π_f`` is refused with a :class:`~balustrade.errors.CodegenError` naming ``pi_f`` (session
13; it used to be replaced by an affine map probed from calls of it, which the C applied
where ``π_f`` differs from it).

The candidate's terminal input is ``π_f(z_N)`` when it lies in ``U ⊖ κ(E)``; otherwise
Python minimizes ``h_f(f(z_N, v, 0))`` over ``U ⊖ κ(E)`` with SLSQP. The C computes that
minimizer in closed form when there is one input and the function is a quadratic in ``v``
(a linear system with a quadratic ``h_f``: the unconstrained minimizer clipped to the
interval ``U ⊖ κ(E)``); for other systems it drops the candidate at such a step
(``<name>_candidate_exact`` returns 0, :class:`~balustrade.codegen.CRobustPCBFSafetyFilter`
records ``values["candidate_exact"] = 0``) — a later (5.15) failure then falls back to the
projected proposal where Python would apply its candidate.

:func:`emit_multiobjective` does the same for Algorithm 6.4 (``bal/multiobj.c``): the
polished slacks of (5.15) and of (6.15) (``<name>_post_slack``, ``<name>_post_problem``),
the candidate (6.14) (``<name>_cand``, the same function as (5.17)). Algorithm 6.3:
:mod:`~balustrade.codegen.emit_mo_lyap`.

Both problems must be compiled for an emittable target. Build the controller with
:data:`EMITTABLE_TARGET` for both: ``RobustPCBFSafetyFilter.build(..., target="robust-sqp",
slack_target="robust-sqp")`` (the SQP preset of :mod:`balustrade.backends.targets`, with
room for the many iterations (5.15) needs when ``h_r > 0``).

Retry chain (issue #16): by default (``full_chain=True``) the C runs each problem's
whole retry chain, as the Python backend does — for ``robust-sqp`` the other Hessian
convexification, then the interior-point solver from a cold start — so the C decides as
the Python controller without a mirror mode. That last retry calls the interior-point
solver's C interface and links its library, shipped with the casadi wheel
(``Emitted.libraries``, :data:`balustrade.backends.emittable.SUPPORTED`; the build flags
are the manifest's ``link_flags``, which :func:`~balustrade.codegen.accelerate` uses). On
the lane change (§8.2) the SQP attempts alone fail the cold (5.15) at ``x_0`` and a few
(5.16)/(6.15) solves that the last retry solves. ``full_chain=False`` gives self-contained
C (only ``libm``) without it; compare that with a Python controller that runs the same
part of the chain (:func:`~balustrade.codegen.mirror_c_retries`).

Recovery steps (issue #14): the controllers' ``recovery_target`` names an attempt of the
chain that leads on their recovery steps (:mod:`balustrade.backends.recovery`); the C runs
it first there too (``bal/problem.c``'s ``P_solve_lead``, ``<name>_SLACK_LEAD``,
``<name>_PROBLEM_LEAD``, and for Algorithm 5.2's (5.16) without a candidate
``<name>_FILTER_LEAD``; 0 when that attempt is not emitted, ``full_chain=False``).
"""

from __future__ import annotations

from pathlib import Path

import casadi as ca
import numpy as np

from balustrade.backends.recovery import recovery_lead
from balustrade.codegen import cfiles as C
from balustrade.codegen import status as S
from balustrade.codegen.emit import (
    Emitted,
    _check_accept_tol,
    _check_identifier,
    _controller_pair,
    _generate,
    _out_dir,
    _Problem,
    _require,
    _spec,
    _write_module,
)
from balustrade.codegen.emit_rapsf import link_flags
from balustrade.control.deploy import (
    MultiobjectiveDeployment,
    RobustDeployment,
    TubeDeployment,
)
from balustrade.control.multiobjective import DECREASE_TOL
from balustrade.control.robust import ABOVE_CANDIDATE_TOL
from balustrade.control.tube_functions import candidate_function, polish_expr
from balustrade.errors import BalustradeError, CodegenError

#: the target to build both problems of Algorithm 5.2 with for C (module docstring)
EMITTABLE_TARGET = "robust-sqp"
_HINT = (f"build the controller with target={EMITTABLE_TARGET!r}, "
         f"slack_target={EMITTABLE_TARGET!r} ({{}}.build)")


def _columns(w: ca.SX, var: dict) -> ca.SX:
    """The variable ``var`` (layout entry: offset, shape) of the stacked vector ``w`` as a
    matrix (column-major, as the layout stacks it)."""
    rows, cols = (list(var["shape"]) + [1, 1])[:2]
    off = int(var["offset"])
    return ca.reshape(w[off: off + rows * cols], rows, cols)


def _post(sym: str, spec: RobustDeployment | MultiobjectiveDeployment, prob: _Problem
          ) -> ca.Function:
    """``sym(w, f) -> (ξ, ξ_N, h_r, h̃)`` on the stacked vector ``w`` of ``prob`` ((5.15)
    or (6.15)): the polished slacks and ``h_r = h̃`` of them
    (:func:`~balustrade.control.tube_functions.polish_expr`, the expression the Python
    controllers evaluate; ``f``, the solver's objective, is not used: a slightly negative
    slack it contains is not certified by the point,
    :meth:`~balustrade.control.robust.RobustPCBFSafetyFilter.h_r`)."""
    w, f = ca.SX.sym("w", prob.nw), ca.SX.sym("f", 1)
    xi_p, xi_N_p, h_tilde = polish_expr(
        spec.X_E, spec.h_f, spec.deltas, spec.alpha_f, spec.slack_norm,
        _columns(w, prob.vars["z"]), _columns(w, prob.vars["xi"]),
        w[int(prob.vars["xi_N"]["offset"])])
    return ca.Function(sym, [w, f], [ca.vec(xi_p), xi_N_p, h_tilde, h_tilde],
                       ["w", "f"], ["xi", "xi_N", "h_r", "h_tilde"])


def _cand(sym: str, spec: TubeDeployment) -> ca.Function:
    """``sym(z, v, ξ) -> (z̃, ṽ, ξ̃, ξ̃_N, h̃(ξ̃), exact)``: the candidate (5.17)/(6.14)
    (:func:`~balustrade.control.tube_functions.candidate_function`, the function the Python
    controllers evaluate). ``π_f`` must accept CasADi symbols (an
    :class:`~balustrade.dsl.policies.AffinePolicy`, a ``casadi.Function``): a numpy-only
    ``π_f`` is refused, not replaced by an affine map identified from calls of it, which
    the C would apply where ``π_f`` is not that map (session 13, docs/vehicles.md)."""
    try:
        return candidate_function(sym, spec.system, spec.X_E, spec.U_E, spec.h_f, spec.pi_f,
                                  spec.deltas, spec.alpha_f, spec.slack_norm,
                                  fit_policy=False)
    except BalustradeError as exc:
        raise CodegenError(f"{sym}: {exc} (the C computes the candidate (5.17)/(6.14) from "
                           "the CasADi expressions of h_f and pi_f)") from exc


def _c_lead(prob: _Problem, recovery: object) -> int:
    """The attempt number in ``bal/problem.c`` (0: the first attempt, ``k``: the k-th
    retry) of the attempt that leads ``prob``'s chain on a recovery step
    (:func:`~balustrade.backends.recovery.recovery_lead`), 0 for none: no recovery target,
    or its attempt not emitted (``full_chain=False`` leaves the interior-point retry out;
    the C then runs the chain in its usual order, as a Python controller without a recovery
    target). The mapping from the chain's retries to the C's attempts is
    :attr:`_Problem.c_attempt` (one rule for this and ``second_solver``)."""
    k = recovery_lead(prob.c, recovery)
    if k is None:
        return 0
    j = prob.c_attempt[k + 1]  # c_attempt[0] is the first solver, [k + 1] retries[k]
    return 0 if j is None else j


def _check_tube(name: str, spec: TubeDeployment, probs: dict[str, _Problem]) -> None:
    """``h_f`` is scalar (the C holds one double for ``ξ_N``, ``h_r``, ``h̃``) and z, v, xi of
    the problems have the shapes of the horizon ``len(deltas)``."""
    nx, nu, N = spec.system.nx, spec.system.nu, len(spec.deltas)
    try:
        h_f = spec.h_f(ca.SX.sym("z", nx))
    except Exception as exc:
        raise CodegenError(f"{name}: h_f failed on a CasADi symbol of shape ({nx}, 1): "
                           f"{exc}") from exc
    if not isinstance(h_f, (ca.SX, ca.MX, ca.DM)) or h_f.numel() != 1:
        raise CodegenError(f"{name}: h_f must be scalar on a state of {nx} "
                           f"entries, got shape {getattr(h_f, 'shape', type(h_f).__name__)}")
    if spec.K is None:
        raise CodegenError(f"{name}: the C applies u = v0 + K(x - z0): the error set needs "
                           "a linear feedback K (not a kappa_fn)")
    for label, prob in probs.items():
        if list(prob.vars["z"]["shape"]) != [nx, N + 1] or \
                int(np.prod(prob.vars["v"]["shape"])) != nu * N:
            raise CodegenError(f"{name}: z, v of {label} have shapes {prob.vars['z']['shape']}"
                               f", {prob.vars['v']['shape']}; expected ({nx}, {N + 1}), "
                               f"({nu}, {N})")
        xi = prob.vars.get("xi")
        if xi is not None and int(np.prod(xi["shape"])) != spec.X_E.H.shape[0] * N:
            raise CodegenError(f"{name}: xi of {label} has shape {xi['shape']}, expected "
                               f"({spec.X_E.H.shape[0]}, {N})")


def _tube_config(cfg: C.Config, name: str, spec: TubeDeployment, U: object) -> None:
    """The ``#define``\\ s shared by bal/robust.c and bal/multiobj.c."""
    nx, nu, N = spec.system.nx, spec.system.nu, len(spec.deltas)
    cfg.define(f"{name}_NX", nx)
    cfg.define(f"{name}_NU", nu)
    cfg.define(f"{name}_N", N)
    cfg.define(f"{name}_N_XI", spec.X_E.H.shape[0] * N, "slacks xi")
    cfg.define(f"{name}_ABOVE_CAND_TOL", repr(float(ABOVE_CANDIDATE_TOL)),
               "(5.15) above the candidate's h~ by more: a failed (5.15)")
    cfg.array(f"{name}_U_LB", U.lb)
    cfg.array(f"{name}_U_UB", U.ub)
    cfg.array(f"{name}_K", np.asarray(spec.K, dtype=float).reshape(nu, nx).T.reshape(-1),
              nu * nx)


def _work_sizes(cfg: C.Config, name: str, syms: list[str]) -> None:
    cfg.comment(f"the work vectors of {', '.join(syms)}")
    for key in ("ARG", "RES", "IW", "W"):
        expr = f"{syms[0]}_SZ_{key}"
        for sym in syms[1:]:
            expr = f"BAL_MAX2({expr}, {sym}_SZ_{key})"
        cfg.define(f"{name}_SZ_{key}", expr)


def _tube_module(name: str, out_dir: Path, spec: TubeDeployment, U: object,
                 libs: list[str], probs: dict[str, _Problem], steps: dict[str, ca.Function],
                 kind: tuple[str, str, tuple[S.Status, ...], str], comment: str,
                 title: str, defines: list[tuple[str, object, str | None]],
                 extra: dict) -> Emitted:
    """The module of a tube-based step, shared by :func:`emit_robust` and
    :func:`emit_multiobjective`: the CasADi code of both problems and of ``steps``, the
    config (the problems, :func:`_tube_config`, ``defines``, the work sizes, the status
    family), the manifest (``extra`` after ``N``) and ``bal/<step>.c``. ``kind`` is
    ``(manifest kind, bal/ file, status family, manifest key of the family)``."""
    manifest_kind, step_file, family, family_key = kind
    nx, nu, N = spec.system.nx, spec.system.nu, len(spec.deltas)
    n_xi = spec.X_E.H.shape[0] * N
    for sym, fn in steps.items():  # the C's buffers (bal/robust.h, bal/multiobj.h)
        sizes = [nx * (N + 1), nu * N, n_xi, 1, 1, 1] if sym.endswith("_cand") else \
            [n_xi, 1, 1, 1]
        got = [fn.numel_out(i) for i in range(fn.n_out())]
        if got != sizes:
            raise CodegenError(f"{name}: {sym} has outputs of {got} entries where the C "
                               f"holds {sizes} (h_f must be scalar, π_f of {nu} entries)")
    files = _generate({k: v for p in probs.values() for k, v in p.functions().items()}
                      | steps, name, out_dir)
    cfg = C.Config()
    for p in probs.values():
        p.config(cfg)
    cfg.comment(f"---- {comment} (bal/{step_file}.h) ----")
    _tube_config(cfg, name, spec, U)
    for macro, value, doc in defines:
        cfg.define(macro, value, doc)
    _work_sizes(cfg, name, list(steps))
    cfg.status(family, f"BAL_{step_file.upper()}_STATUS_CODES")
    libs = [*libs, *(lib for p in probs.values() for lib in p.libraries)]
    manifest = {"kind": manifest_kind, "nx": spec.system.nx, "nu": spec.system.nu,
                "N": len(spec.deltas), **extra,
                "link_flags": list(link_flags(tuple(sorted(set(libs))))),
                "U": {"lb": list(map(float, U.lb)), "ub": list(map(float, U.ub))},
                "problems": {k: p.manifest() for k, p in probs.items()},
                family_key: S.manifest(family)}
    return _write_module(name, out_dir, title, cfg,
                         [*(("problem", p.P) for p in probs.values()), (step_file, name)],
                         files, manifest, tuple(sorted(set(libs))))


def emit_robust(controller: object, name: str, out_dir: str | Path,
                allow_external: bool = False, accept_tol: float | None = None,
                full_chain: bool = True) -> Emitted:
    """Emit Algorithm 5.2 of a :class:`~balustrade.control.robust.RobustPCBFSafetyFilter`
    built with ``target="robust-sqp", slack_target="robust-sqp"`` (:data:`EMITTABLE_TARGET`)
    as one C call per control step: ``<name>_step(x, u_p, u_out, h_out, status, work)``
    (``bal/robust.h``), ``h_out`` = ``h_r(x_k)``; ``<name>_h_cand`` the ``h̃`` of the
    candidate (5.17). ``U`` must be a Box (the projected proposal clips), ``κ`` linear
    (``E.K``). Solves are accepted and retried as in
    :func:`~balustrade.codegen.emit_problem`; only ``BAL_OK`` counts as a success, as
    only ``optimal`` does in Python. ``allow_external``: admit a first attempt whose C links
    a library. ``full_chain`` (default True): the retries whose C links a library (the
    interior-point last resort) are emitted too, so the C runs the chain Python runs
    (module docstring); False: self-contained C without them."""
    _check_identifier(name)
    _check_accept_tol(name, accept_tol)
    spec = _spec(controller, name, RobustDeployment, "RobustPCBFSafetyFilter")
    try:
        slack, filt, U, libs = _controller_pair(
            name, spec.problems.get("slack"), spec.problems.get("filter"), spec.U,
            ("robust slack problem (5.15)", "robust filter problem (5.16)"), allow_external)
    except CodegenError as exc:
        raise CodegenError(f"{exc}; for Algorithm 5.2: "
                           f"{_HINT.format('RobustPCBFSafetyFilter')}") from exc
    out_dir = _out_dir(out_dir, name)
    s = _Problem(slack, f"{name}_slack", f"robust slack problem (5.15) {slack.ocp.name!r}",
                 name, accept_tol, full_chain)
    f = _Problem(filt, f"{name}_filter", f"robust filter (5.16) {filt.ocp.name!r}", name,
                 accept_tol, full_chain)
    _require(name, {"(5.15) parameter": (s.params, ["x0"]),
                    "(5.15) variable": (s.vars, ["z", "v", "xi", "xi_N"]),
                    "(5.16) parameter": (f.params, ["x0", "u_p", "xi", "xi_N"]),
                    "(5.16) variable": (f.vars, ["z", "v"])},
             "build the problems with balustrade.problems.robust")
    _check_tube(name, spec, {"(5.15)": s, "(5.16)": f})
    N = len(spec.deltas)
    steps = {f"{name}_post": _post(f"{name}_post", spec, s),
             f"{name}_cand": _cand(f"{name}_cand", spec)}
    return _tube_module(
        name, out_dir, spec, U, libs, {"slack": s, "filter": f}, steps,
        ("robust", "robust", S.ROBUST, "robust_status"),
        f"Algorithm 5.2, the robust PCBF step {name}: (5.15) then (5.16)",
        "Algorithm 5.2, the robust PCBF filter (5.15)+(5.16)",
        [(f"{name}_SLACK_LEAD", _c_lead(s, spec.recovery_target),
          "the (5.15) attempt run first on a recovery step (0: none)"),
         (f"{name}_FILTER_LEAD", _c_lead(f, spec.recovery_target),
          "the (5.16) attempt run first when there is no candidate (0: none)")],
        {"n_xi": spec.X_E.H.shape[0] * N})


def emit_multiobjective(controller: object, name: str, out_dir: str | Path,
                        allow_external: bool = False, accept_tol: float | None = None,
                        full_chain: bool = True) -> Emitted:
    """Emit Algorithm 6.4 of a
    :class:`~balustrade.control.multiobjective.MultiobjectivePCBFController` built with
    ``target="robust-sqp", slack_target="robust-sqp"`` as one C call per control step:
    ``<name>_step(x, u_p, u_out, status, work)`` (``bal/multiobj.h``); ``<name>_values``
    gives ``h_cand``, ``bound``, ``h_tilde`` of the last step and ``h_tilde_rejected``
    (NaN unless it was ``problem_above_bound``). ``record_h_r`` (an extra
    (5.15) solve per step, for plots) is not emitted. ``allow_external`` and ``full_chain``
    as in :func:`emit_robust`.

    Algorithm 6.3 (:class:`~balustrade.control.multiobjective.
    MultiobjectiveLyapunovController`):
    :func:`~balustrade.codegen.emit_mo_lyap.emit_mo_lyapunov`."""
    _check_identifier(name)
    _check_accept_tol(name, accept_tol)
    spec = _spec(controller, name, MultiobjectiveDeployment, "MultiobjectivePCBFController")
    try:
        slack, prob, U, libs = _controller_pair(
            name, spec.problems.get("slack"), spec.problems.get("problem"), spec.U,
            ("robust slack problem (5.15)", "multiobjective problem (6.15)"),
            allow_external)
    except CodegenError as exc:
        raise CodegenError(f"{exc}; for Algorithm 6.4: "
                           f"{_HINT.format('MultiobjectivePCBFController')}") from exc
    if spec.record_h_r:
        raise CodegenError(f"{name}: record_h_r=True (an extra (5.15) solve per step for "
                           "plots) is not emitted; build the controller without it")
    out_dir = _out_dir(out_dir, name)
    s = _Problem(slack, f"{name}_slack", f"robust slack problem (5.15) {slack.ocp.name!r}",
                 name, accept_tol, full_chain)
    p = _Problem(prob, f"{name}_problem", f"multiobjective (6.15) {prob.ocp.name!r}", name,
                 accept_tol, full_chain)
    _require(name, {"(5.15) parameter": (s.params, ["x0"]),
                    "(5.15) variable": (s.vars, ["z", "v", "xi", "xi_N"]),
                    "(6.15) parameter": (p.params, ["x0", "u_p", "bound"]),
                    "(6.15) variable": (p.vars, ["z", "v", "xi", "xi_N"])},
             "build the problems with balustrade.problems.multiobjective")
    _check_tube(name, spec, {"(5.15)": s, "(6.15)": p})
    steps = {f"{name}_post_slack": _post(f"{name}_post_slack", spec, s),
             f"{name}_post_problem": _post(f"{name}_post_problem", spec, p),
             f"{name}_cand": _cand(f"{name}_cand", spec)}
    return _tube_module(
        name, out_dir, spec, U, libs, {"slack": s, "problem": p}, steps,
        ("multiobjective", "multiobj", S.MULTIOBJ, "multiobj_status"),
        f"Algorithm 6.4, the multiobjective robust PCBF step {name}",
        "Algorithm 6.4, the multiobjective robust PCBF controller (5.15)+(6.15)",
        [(f"{name}_RHO", C.c_double(spec.rho), "rho of (6.15g)"),
         (f"{name}_SLACK_LEAD", _c_lead(s, spec.recovery_target),
          "the (5.15) attempt run first at the first step (0: none)"),
         (f"{name}_PROBLEM_LEAD", _c_lead(p, spec.recovery_target),
          "the (6.15) attempt run first until one converges (0: none)"),
         (f"{name}_BOUND_TOL", C.c_double(spec.bound_tol), None),
         (f"{name}_DECREASE_TOL", C.c_double(DECREASE_TOL),
          "a converged (6.15) whose polished h~ exceeds the bound by more (relative) fails"),
         (f"{name}_XI_SUM", int("xi_sum" in p.vars),
          "1: (6.15g) in running-sum form, variable xi_sum"),
         (f"{name}_CANDIDATE_DUALS", int(bool(getattr(spec, "candidate_duals", False))),
          "1: ordinary (6.15) start from the candidate with the previous multipliers"),
         (f"{name}_CANDIDATE_SECOND", int(bool(getattr(spec, "candidate_second", False))),
          "1: a failed ordinary (6.15) is tried again from the candidate with the "
          "previous multipliers")],
        {"rho": float(spec.rho), "bound_tol": float(spec.bound_tol)})


__all__ = ["EMITTABLE_TARGET", "emit_multiobjective", "emit_robust"]
