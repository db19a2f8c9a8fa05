"""Robust predictive control formulations (thesis Sections 2.5 and 5.5).

* :func:`robust_mpc_problem` — (2.14): nominal prediction from ``z_0 = x_k`` with the reachable-set
  tightenings ``X ⊖ E_i``, ``U ⊖ K E_i``, ``X_f ⊖ E_N``;
* :func:`tube_mpc_problem` — (2.15): ``x_k ∈ z_0 ⊕ E`` with ``z_0`` a decision variable,
  ``X ⊖ E``, ``U ⊖ K E``, ``z_N ∈ X_f``; apply ``v*_0 + K(x_k − z*_0)``;
* :func:`robust_pcbf_slack_problem` — (5.15): ``h_r(x_k)``;
* :func:`robust_pcbf_filter_problem` — (5.16): the filter with the slacks of (5.15) fixed;
* :func:`fuel_objective` — ``J = Σ_i ‖v_i‖₁``, the rendezvous objective of (5.16)/(6.15).

The terminal CBF SDP (6.17) with a domain level is solved by
:func:`~balustrade.design.terminal_cbf.terminal_cbf_with_domain`.

The numerical steps between solves — the candidate (5.17), the terminal input, the slack
polishing and ``h̃(ξ)`` — are in :mod:`balustrade.control.robust_steps`.

The robustly tightened constraint function is ``c_x^E(z) = A_x z − b_x + s_E`` (SPEC §1.4): the
builders pass ``X ⊖ E`` (a :class:`~balustrade.dsl.sets.Polytope`) to ``state_constraint``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import casadi as ca
import numpy as np

from balustrade._checks import as_matrix, check_callable, check_horizon, check_instance
from balustrade.dsl import OCP, Polytope, System, squared_norm, sum_norms
from balustrade.dsl.costs import Cost
from balustrade.dsl.error_sets import ErrorSet, reachable_tightened_sets, tighten
from balustrade.errors import moved_names
from balustrade.problems._args import (
    check_norm_order,
    check_pcbf_args,
    check_system_sets,
    check_weights,
    nonnegative,
    positive,
)
from balustrade.problems._costs import trajectory_cost

Objective = Callable[[OCP, dict], object]


# -- (2.14), (2.15) -------------------------------------------------------------------------
def robust_mpc_problem(system: System, X: Polytope, U: Polytope, Xf: Polytope, N: int,
                       A_K: np.ndarray, K: np.ndarray, W: Polytope, Q: np.ndarray,
                       R: np.ndarray, P: np.ndarray, G: np.ndarray | None = None,
                       name: str = "robust_mpc") -> OCP:
    """(2.14): ``min Σ l(z_i, v_i) + l_f(z_N)`` s.t. ``z_0 = x_k``, nominal dynamics,
    ``z_i ∈ X ⊖ E_i``, ``v_i ∈ U ⊖ K E_i``, ``z_N ∈ X_f ⊖ E_N`` with
    ``E_i = ⊕_{j<i} A_K^j G W`` (support-function tightenings). Parameter ``x0``."""
    check_system_sets(name, system, X, U, polytope=True, Xf=Xf)
    N = check_horizon(N, name)
    Q, R, P = check_weights(name, system.nx, system.nu, Q, R, P)
    A_K = as_matrix(A_K, f"{name}: A_K", (system.nx, system.nx))
    K = as_matrix(K, f"{name}: K", (system.nu, system.nx))
    Xs = reachable_tightened_sets(X, A_K, W, N, G, name="X")
    Us = reachable_tightened_sets(U, A_K, W, N, G, K=K, name="U")
    Xf_N = reachable_tightened_sets(Xf, A_K, W, N, G, name="Xf")[N]
    ocp = OCP(system, N, name=name, state_name="z", input_name="v")
    ocp.initial_state(ocp.parameter("x0", system.nx))
    ocp.dynamics()
    ocp.state_constraint(Xs[:N])
    ocp.input_constraint(Us[:N])
    ocp.terminal_constraint(Xf_N)
    ocp.minimize(trajectory_cost(ocp.x, ocp.u, Q, R, P))
    return ocp


def tube_mpc_problem(system: System, X: Polytope, U: Polytope, Xf: Polytope, N: int,
                     error: ErrorSet, Q: np.ndarray, R: np.ndarray, P: np.ndarray,
                     name: str = "tube_mpc") -> OCP:
    """(2.15): ``x_k − z_0 ∈ E`` (``z_0`` free), nominal dynamics, ``z_i ∈ X ⊖ E``,
    ``v_i ∈ U ⊖ K E``, ``z_N ∈ X_f``; apply ``v*_0 + K(x_k − z*_0)``. Parameter ``x0``."""
    check_system_sets(name, system, X, U, polytope=True)
    check_system_sets(name, system, Xf=Xf)
    N = check_horizon(N, name)
    Q, R, P = check_weights(name, system.nx, system.nu, Q, R, P)
    check_instance(error, ErrorSet, f"{name}: error")
    ocp = OCP(system, N, name=name, state_name="z", input_name="v")
    ocp.initial_tube(ocp.parameter("x0", system.nx), error.E)
    ocp.dynamics()
    ocp.state_constraint(error.tighten_state(X))
    ocp.input_constraint(error.tighten_input(U))
    ocp.terminal_constraint(Xf)
    ocp.minimize(trajectory_cost(ocp.x, ocp.u, Q, R, P))
    return ocp


# -- robust PCBF (5.15), (5.16) -----------------------------------------------------------------
@dataclass(frozen=True)
class RobustSets:
    """``X ⊖ E`` and ``U ⊖ κ(E)`` used by (5.15)–(5.17), (6.15)."""

    X_E: Polytope
    U_E: Polytope


def robust_sets(X: Polytope, U: Polytope, error: ErrorSet,
                U_tight: Polytope | None = None) -> RobustSets:
    """``X ⊖ E`` and ``U ⊖ K E`` (or the user's ``U_tight`` for a nonlinear κ)."""
    check_instance(error, ErrorSet, "robust_sets: error")
    if U_tight is not None:
        check_instance(U_tight, Polytope, "robust_sets: U_tight")
    X_E = tighten(X, error.E, name=f"{X.name}⊖E")
    U_E = U_tight if U_tight is not None else error.tighten_input(U, name=f"{U.name}⊖KE")
    return RobustSets(X_E, U_E)


def _tube_blocks(ocp: OCP, system: System, sets: RobustSets, error: ErrorSet) -> ca.SX:
    x0 = ocp.parameter("x0", system.nx)
    ocp.initial_tube(x0, error.E)                       # (5.15b) x_k − z_0 ∈ E
    ocp.dynamics()                                      # (5.15c) z_{i+1} = f(z_i, v_i, 0)
    ocp.input_constraint(sets.U_E)                      # (5.15d) v_i ∈ U ⊖ κ(E)
    return x0


def robust_pcbf_slack_problem(system: System, X: Polytope, U: Polytope, h_f: Callable,
                              N: int, deltas: np.ndarray, error: ErrorSet,
                              alpha_f: float = 1e6, slack_norm: int | float = 1,
                              U_tight: Polytope | None = None,
                              name: str = "robust_pcbf_slack") -> OCP:
    """(5.15): ``h_r(x_k) = min α_f ξ_N + Σ_i ‖ξ_i‖`` s.t. (5.15b–f).

    Parameter ``x0``; variables ``z``, ``v``, ``xi`` (rows of ``c_x`` × N, ``>= 0``), ``xi_N``.
    """
    N, deltas = check_pcbf_args(name, system, X, U, h_f, N, deltas, polytope=True)
    alpha_f = positive(alpha_f, f"{name}: alpha_f")
    check_norm_order(slack_norm, f"{name}: slack_norm")
    sets = robust_sets(X, U, error, U_tight)
    ocp = OCP(system, N, name=name, state_name="z", input_name="v")
    _tube_blocks(ocp, system, sets, error)
    xi = ocp.variable("xi", sets.X_E.n_rows, N, lb=0.0, role="slack")
    xi_N = ocp.variable("xi_N", 1, 1, lb=0.0, role="slack")
    ocp.state_constraint(sets.X_E, tightening=deltas, slack=xi)    # (5.15e)
    ocp.terminal_cbf(h_f, slack=xi_N)                              # (5.15f)
    ocp.minimize(alpha_f * xi_N + sum_norms(xi, slack_norm, label="slack"))
    return ocp


def robust_pcbf_filter_problem(system: System, X: Polytope, U: Polytope, h_f: Callable,
                               N: int, deltas: np.ndarray, error: ErrorSet,
                               eps: float = 1e-6, objective: Objective | None = None,
                               U_tight: Polytope | None = None,
                               name: str = "robust_pcbf_filter") -> OCP:
    """(5.16): ``min J`` s.t. (5.16b–d) and the slacks fixed to the parameters ``xi``, ``xi_N``
    (the optimum of (5.15)) plus the margin ``eps``.

    Default ``J = ‖u_p − (v_0 + K(x_k − z_0))‖²`` (the safety-filter cost of (5.16) with the
    SPEC's parenthesization; squared: same minimizer, QP). ``objective(ocp, syms)`` may return
    any cost; ``syms`` holds ``x0``, ``u_p``, ``z``, ``v``, ``u0`` (the applied input expression).
    Parameters ``x0``, ``u_p``, ``xi``, ``xi_N``.
    """
    N, deltas = check_pcbf_args(name, system, X, U, h_f, N, deltas, polytope=True)
    eps = nonnegative(eps, f"{name}: eps")
    if objective is not None:
        check_callable(objective, f"{name}: objective")
    sets = robust_sets(X, U, error, U_tight)
    ocp = OCP(system, N, name=name, state_name="z", input_name="v")
    x0 = _tube_blocks(ocp, system, sets, error)
    u_p = ocp.parameter("u_p", system.nu)
    xi = ocp.parameter("xi", sets.X_E.n_rows, N, lb=0.0)   # ξ >= 0 as in (5.15e)
    xi_N = ocp.parameter("xi_N", 1, lb=0.0)
    ocp.state_constraint(sets.X_E, tightening=deltas, slack=xi + eps)   # (5.16e)
    ocp.terminal_cbf(h_f, slack=xi_N + eps)                             # (5.16f)
    syms = _syms(ocp, x0, u_p, error)
    ocp.minimize(objective(ocp, syms) if objective is not None
                 else squared_norm(syms["u0"] - u_p, label="filter"))
    return ocp


def _syms(ocp: OCP, x0: ca.SX, u_p: ca.SX | None, error: ErrorSet) -> dict:
    u0 = ocp.u[:, 0]
    if error.K is not None:
        u0 = u0 + ca.mtimes(ca.DM(error.K), x0 - ocp.x[:, 0])
    return {"x0": x0, "u_p": u_p, "z": ocp.x, "v": ocp.u, "u0": u0}


def fuel_objective(ocp: OCP, syms: dict) -> Cost:
    """``J = Σ_i ‖v_i‖₁`` (rendezvous, SPEC §3.4)."""
    return sum_norms(syms["v"], 1, label="fuel")

#: names that moved out of this module (issue #13): deprecated aliases (errors.moved_names)
__getattr__ = moved_names(__name__, {
    "terminal_cbf_with_domain": "balustrade.design.terminal_cbf",
    "Candidate": "balustrade.control.robust_steps",
    "minimal_slacks": "balustrade.control.robust_steps",
    "polished_slacks": "balustrade.control.robust_steps",
    "robust_candidate": "balustrade.control.robust_steps",
    "slack_cost": "balustrade.control.robust_steps",
    "terminal_input": "balustrade.control.robust_steps",
})
