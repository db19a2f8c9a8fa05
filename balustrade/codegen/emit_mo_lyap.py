"""Emit Algorithm 6.3, the multiobjective Lyapunov controller of the linear design (6.10)
(thesis Section 6.3.2), as one C call per control step.

:func:`emit_mo_lyapunov` writes the module of :mod:`~balustrade.codegen.emit` (``bal/``,
``<name>_config.h``, ``<name>.h/.c``, ``<name>_casadi.c/.h``, ``<name>.json``) with the step
``<name>_step(x, u_p, u_out, status, work)`` of ``bal/multiobj_lyap.c``: the decisions and
fallbacks of :class:`~balustrade.control.multiobjective.MultiobjectiveLyapunovController`,
the linear algebra between the solves as three emitted CasADi functions:

* ``<name>_switch(x, x_prev, u_prev, v_prev)`` — ``w = x − A x_prev − B u_prev``, the warm
  starts ``ξ_c`` (6.11) and ``ξ_f`` (6.12), ``V`` (6.2) of both, the margin
  ``max(H_f x − h_f)`` of ``x ∈ X_f`` and the largest violation of (6.3b–g) by ``ξ_f``'s
  rollout (the rows ``H z <= h`` of ``X ⊖ E_i``, ``U ⊖ K E_i``, ``X_f ⊖ E_N``); the C
  picks ``ξ_f`` when ``x ∈ X_f`` (tolerance :data:`XF_TOL`), ``V(ξ_f) <= V(ξ_c)`` and the
  violation is at most :data:`ADMISSIBLE_TOL` — the tolerances of
  :meth:`~balustrade.problems.multiobjective.LinearLyapunovDesign.switch`;
* ``<name>_bound(x, ũ)`` — the right side of (6.3h) ``V((x, ũ)) − (1 − ρ) l(x, ũ_0)`` and
  the rollout ``φ(x, ũ)``, the warm start ``(v, z)`` of (6.10);
* ``<name>_V(x, v)`` — ``V((x, v))`` of the applied plan (``values["V"]``).

Both problems must be compiled for an emittable target. :data:`EMITTABLE_TARGET` is
``"convex-qp"`` (an SQP over a dual active-set QP solver: (6.10) is a QP with one convex
quadratic row, solved in a few iterations); its C links that QP solver's library from the
casadi wheel (:func:`~balustrade.codegen.emit_rapsf.link_flags`, also in the manifest's
``link_flags``). The controller's default target ``"exact"`` (an interior-point NLP
solver) emits too: its C links the interior-point library shipped in the casadi wheel (the
manifest's ``link_flags``; tested C = Python on a closed loop). Either way Python on the
target and the C run the same solver chain (:func:`~balustrade.codegen.runtime.
mirror_c_retries`), so their answers agree; a target without a C form (``"cvxpy"``, the
direct conic engines) is refused with the name of :data:`EMITTABLE_TARGET`.
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
from balustrade.control.deploy import LyapunovDeployment
from balustrade.errors import CodegenError

#: the target to build :class:`~balustrade.control.multiobjective.
#: MultiobjectiveLyapunovController` with for C (module docstring)
EMITTABLE_TARGET = "convex-qp"
#: the tolerances of ``LinearLyapunovDesign.switch``: ``X_f.contains(x, 1e-12)`` and
#: ``admissible(x, ξ_f)`` (``tol=1e-9``)
XF_TOL = 1e-12
ADMISSIBLE_TOL = 1e-9


def _quad(a: ca.SX, W: np.ndarray) -> ca.SX:
    return ca.mtimes([a.T, ca.DM(W), a])


def _rollout(spec: LyapunovDeployment, x: ca.SX, u: ca.SX) -> ca.SX:
    """``φ(x, u; i)``, ``i ∈ I[0, cols(u)]``, as columns (nominal model)."""
    A, B = ca.DM(spec.A), ca.DM(spec.B)
    cols = [x]
    for i in range(u.shape[1]):
        cols.append(ca.mtimes(A, cols[-1]) + ca.mtimes(B, u[:, i]))
    return ca.horzcat(*cols)


def _V(spec: LyapunovDeployment, x: ca.SX, u: ca.SX) -> ca.SX:
    """(6.2): ``½ [Σ_i (φ_iᵀQφ_i + u_iᵀRu_i) + φ_NᵀPφ_N]``."""
    z = _rollout(spec, x, u)
    total = ca.SX(0)
    for i in range(u.shape[1]):
        total += _quad(z[:, i], spec.Q) + _quad(u[:, i], spec.R)
    return 0.5 * (total + _quad(z[:, u.shape[1]], spec.P))


def _max_violation(H: np.ndarray, h: np.ndarray, y: ca.SX) -> ca.SX:
    return ca.mmax(ca.mtimes(ca.DM(np.asarray(H, dtype=float)), y)
                   - ca.DM(np.asarray(h, dtype=float)))


def _switch(sym: str, spec: LyapunovDeployment) -> ca.Function:
    """``sym(x, x_prev, u_prev, v_prev) -> (ξ_c, ξ_f, V_c, V_f, m_xf, m_adm)`` (module
    docstring; (6.11), (6.12), (6.2), (6.3b–g))."""
    nx, nu, N = spec.A.shape[0], spec.B.shape[1], spec.N
    K, A_K = ca.DM(spec.K), ca.DM(spec.A + spec.B @ spec.K)
    x, xp = ca.SX.sym("x", nx), ca.SX.sym("x_prev", nx)
    up, vp = ca.SX.sym("u_prev", nu), ca.SX.sym("v_prev", nu, N)
    w = x - ca.mtimes(ca.DM(spec.A), xp) - ca.mtimes(ca.DM(spec.B), up)
    cols, e = [], w
    for i in range(N - 1):                                   # (6.11) with the SPEC fixes
        cols.append(vp[:, i + 1] + ca.mtimes(K, e))
        e = ca.mtimes(A_K, e)
    head = ca.horzcat(*cols) if cols else ca.SX(nu, 0)
    last = ca.mtimes(K, _rollout(spec, x, head)[:, N - 1])
    xi_c = ca.horzcat(head, last)
    f_cols, z = [], x                                        # (6.12)
    for _ in range(N):
        f_cols.append(ca.mtimes(K, z))
        z = ca.mtimes(A_K, z)
    xi_f = ca.horzcat(*f_cols)
    zf = _rollout(spec, x, xi_f)
    viol = [_max_violation(spec.Xs[i].H, spec.Xs[i].h, zf[:, i]) for i in range(N)]
    viol += [_max_violation(spec.Us[i].H, spec.Us[i].h, xi_f[:, i]) for i in range(N)]
    viol.append(_max_violation(spec.Xf_N.H, spec.Xf_N.h, zf[:, N]))
    return ca.Function(sym, [x, xp, up, vp],
                       [ca.vec(xi_c), ca.vec(xi_f), _V(spec, x, xi_c), _V(spec, x, xi_f),
                        _max_violation(spec.Xf.H, spec.Xf.h, x), ca.mmax(ca.vertcat(*viol))],
                       ["x", "x_prev", "u_prev", "v_prev"],
                       ["xi_c", "xi_f", "V_c", "V_f", "m_xf", "m_adm"])


def _bound(sym: str, spec: LyapunovDeployment) -> ca.Function:
    """``sym(x, ũ) -> (bound, z)``: the right side of (6.3h) and ``φ(x, ũ)``."""
    nx, nu, N = spec.A.shape[0], spec.B.shape[1], spec.N
    x, u = ca.SX.sym("x", nx), ca.SX.sym("u", nu, N)
    stage = 0.5 * (_quad(x, spec.Q) + _quad(u[:, 0], spec.R))
    bound = _V(spec, x, u) - (1.0 - spec.rho) * stage
    return ca.Function(sym, [x, u], [bound, ca.vec(_rollout(spec, x, u))], ["x", "u"],
                       ["bound", "z"])


def _value(sym: str, spec: LyapunovDeployment) -> ca.Function:
    nx, nu, N = spec.A.shape[0], spec.B.shape[1], spec.N
    x, v = ca.SX.sym("x", nx), ca.SX.sym("v", nu, N)
    return ca.Function(sym, [x, v], [_V(spec, x, v)], ["x", "v"], ["V"])


def _check_shapes(name: str, spec: LyapunovDeployment, probs: dict[str, _Problem]) -> None:
    nx, nu, N = spec.A.shape[0], spec.B.shape[1], spec.N
    for label, prob in probs.items():
        if list(prob.vars["z"]["shape"]) != [nx, N + 1] or \
                list(prob.vars["v"]["shape"]) != [nu, N]:
            raise CodegenError(f"{name}: z, v of {label} have shapes {prob.vars['z']['shape']}"
                               f", {prob.vars['v']['shape']}; expected ({nx}, {N + 1}), "
                               f"({nu}, {N})")


def emit_mo_lyapunov(controller: object, name: str, out_dir: str | Path,
                     allow_external: bool = True, accept_tol: float | None = None
                     ) -> Emitted:
    """Emit Algorithm 6.3 of a
    :class:`~balustrade.control.multiobjective.MultiobjectiveLyapunovController` built with
    ``target="convex-qp"`` (:data:`EMITTABLE_TARGET`) as one C call per control step:
    ``<name>_step(x, u_p, u_out, status, work)`` (``bal/multiobj_lyap.h``);
    ``<name>_values`` gives ``switch``, ``V_bound`` and ``V`` of the last step.
    ``allow_external`` (default True) admits a QP solver whose C links a library
    (:func:`~balustrade.codegen.emit_rapsf.link_flags`, the manifest's ``link_flags``)."""
    _check_identifier(name)
    _check_accept_tol(name, accept_tol)
    spec = _spec(controller, name, LyapunovDeployment, "MultiobjectiveLyapunovController")
    try:
        init, prob, U, libs = _controller_pair(
            name, spec.problems.get("init"), spec.problems.get("problem"), spec.U,
            ("initialization (6.3) without (6.3h)", "multiobjective problem (6.10)"),
            allow_external)
    except CodegenError as exc:
        raise CodegenError(f"{exc}; for Algorithm 6.3 build the controller with "
                           f"MultiobjectiveLyapunovController.build(..., "
                           f"target={EMITTABLE_TARGET!r})") from exc
    out_dir = _out_dir(out_dir, name)
    s = _Problem(init, f"{name}_first", f"initialization (6.3) {init.ocp.name!r}", name,
                 accept_tol)
    p = _Problem(prob, f"{name}_problem", f"multiobjective Lyapunov (6.10) "
                 f"{prob.ocp.name!r}", name, accept_tol)
    _require(name, {"(6.3) parameter": (s.params, ["x0", "u_p"]),
                    "(6.3) variable": (s.vars, ["z", "v"]),
                    "(6.10) parameter": (p.params, ["x0", "u_p", "bound"]),
                    "(6.10) variable": (p.vars, ["z", "v"])},
             "build the problems with multiobjective_lyapunov_problem")
    _check_shapes(name, spec, {"(6.3)": s, "(6.10)": p})
    nx, nu, N = spec.A.shape[0], spec.B.shape[1], spec.N
    steps = {f"{name}_switch": _switch(f"{name}_switch", spec),
             f"{name}_bound": _bound(f"{name}_bound", spec),
             f"{name}_V": _value(f"{name}_V", spec)}
    files = _generate(s.functions() | p.functions() | steps, name, out_dir)
    cfg = C.Config()
    s.config(cfg)
    p.config(cfg)
    cfg.comment(f"---- Algorithm 6.3, the multiobjective Lyapunov step {name} "
                "(bal/multiobj_lyap.h) ----")
    cfg.define(f"{name}_NX", nx)
    cfg.define(f"{name}_NU", nu)
    cfg.define(f"{name}_N", N)
    cfg.array(f"{name}_U_LB", U.lb)
    cfg.array(f"{name}_U_UB", U.ub)
    cfg.define(f"{name}_BOUND_TOL", C.c_double(spec.bound_tol), "margin of (6.3h)")
    cfg.define(f"{name}_XF_TOL", C.c_double(XF_TOL), "x in X_f of the switching rule")
    cfg.define(f"{name}_ADM_TOL", C.c_double(ADMISSIBLE_TOL), "(6.3b-g) of xi_f")
    cfg.comment(f"the work vectors of {', '.join(steps)}")
    for key in ("ARG", "RES", "IW", "W"):
        expr = f"{name}_switch_SZ_{key}"
        for sym in (f"{name}_bound", f"{name}_V"):
            expr = f"BAL_MAX2({expr}, {sym}_SZ_{key})"
        cfg.define(f"{name}_SZ_{key}", expr)
    cfg.status(S.MO_LYAP, "BAL_MULTIOBJ_LYAP_STATUS_CODES")
    libs = tuple(sorted(set(libs)))
    manifest = {"kind": "mo_lyapunov", "nx": nx, "nu": nu, "N": N, "rho": float(spec.rho),
                "bound_tol": float(spec.bound_tol), "link_flags": list(link_flags(libs)),
                "U": {"lb": list(map(float, U.lb)), "ub": list(map(float, U.ub))},
                "problems": {"init": s.manifest(), "problem": p.manifest()},
                "mo_lyap_status": S.manifest(S.MO_LYAP)}
    return _write_module(name, out_dir, "Algorithm 6.3, the multiobjective Lyapunov "
                         "controller (6.3)+(6.10)", cfg,
                         [("problem", s.P), ("problem", p.P), ("multiobj_lyap", name)],
                         files, manifest, libs)


__all__ = ["ADMISSIBLE_TOL", "EMITTABLE_TARGET", "XF_TOL", "emit_mo_lyapunov"]
