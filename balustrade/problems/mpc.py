"""Baseline predictive controllers of thesis Chapter 2.

* :func:`mpc_problem` — nominal MPC (2.9);
* :func:`soft_mpc_problem` — soft-constrained MPC (2.11) with an exact-penalty slack cost;
* :func:`predictive_safety_filter` — the predictive safety filter (2.19);
* :func:`cbf_filter_problem` — the one-step CBF safety filter (2.20).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from balustrade._checks import as_scalar, check_callable, check_horizon
from balustrade.dsl import OCP, Set, System, squared_norm, sum_norms
from balustrade.errors import BalustradeError
from balustrade.problems._args import (
    check_norm_order,
    check_system_sets,
    check_weights,
    positive,
)
from balustrade.problems._costs import trajectory_cost


def _check(name: str, system: System, X: Set, U: Set, Xf: Set | None, N: int,
           Q: np.ndarray, R: np.ndarray, P: np.ndarray
           ) -> tuple[int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    check_system_sets(name, system, X, U)
    if Xf is not None:
        check_system_sets(name, system, Xf=Xf)
    N = check_horizon(N, name)
    return N, check_weights(name, system.nx, system.nu, Q, R, P)


def mpc_problem(system: System, X: Set, U: Set, Xf: Set | None, N: int, Q: np.ndarray,
                R: np.ndarray, P: np.ndarray, name: str = "mpc") -> OCP:
    """(2.9): ``min Σ l(x_i, u_i) + l_f(x_N)`` with quadratic ``l``, ``l_f``, s.t. ``x_0 = x_k``,
    dynamics, ``x_i ∈ X``, ``u_i ∈ U``, ``x_N ∈ X_f``. Parameter: ``x0``."""
    N, (Q, R, P) = _check(name, system, X, U, Xf, N, Q, R, P)
    ocp = OCP(system, N, name=name)
    ocp.initial_state(ocp.parameter("x0", system.nx))
    ocp.dynamics()
    ocp.input_constraint(U)
    ocp.state_constraint(X)
    if Xf is not None:
        ocp.terminal_constraint(Xf)
    ocp.minimize(trajectory_cost(ocp.x, ocp.u, Q, R, P))
    return ocp


def soft_mpc_problem(system: System, X: Set, U: Set, Xf: Set | None, N: int, Q: np.ndarray,
                     R: np.ndarray, P: np.ndarray, penalty: float = 1e4,
                     slack_norm: int | float = 1, name: str = "soft_mpc") -> OCP:
    """(2.11): (2.9) with ``x_i ∈ X(ξ_i)``, ``x_N ∈ X_f(ξ_N)``, ``ξ >= 0`` and the slack cost
    ``l_ξ = penalty · Σ‖ξ_i‖`` (exact for ``penalty`` above the dual norm of the hard
    problem's multipliers, Theorem 2.22). Feasible for every ``x_k``."""
    N, (Q, R, P) = _check(name, system, X, U, Xf, N, Q, R, P)
    penalty = positive(penalty, f"{name}: penalty")
    check_norm_order(slack_norm, f"{name}: slack_norm")
    ocp = OCP(system, N, name=name)
    ocp.initial_state(ocp.parameter("x0", system.nx))
    ocp.dynamics()
    ocp.input_constraint(U)
    xi = ocp.state_constraint(X, slack="variable")
    cost = trajectory_cost(ocp.x, ocp.u, Q, R, P) \
        + penalty * sum_norms(xi, slack_norm, label="slack")
    if Xf is not None:
        xi_N = ocp.terminal_constraint(Xf, slack="variable")
        cost = cost + penalty * sum_norms(xi_N, slack_norm, label="terminal_slack")
    ocp.minimize(cost)
    return ocp


def predictive_safety_filter(system: System, X: Set, U: Set, Xf: Set, N: int,
                             name: str = "psf") -> OCP:
    """(2.19): ``min ‖u_0 − u_p‖²`` subject to the constraints of (2.9) (squared Euclidean
    norm, SPEC §2.5 [Default]: same minimizer as the norm). Parameters: ``x0``, ``u_p``."""
    check_system_sets(name, system, X, U, Xf=Xf)
    N = check_horizon(N, name)
    ocp = OCP(system, N, name=name)
    ocp.initial_state(ocp.parameter("x0", system.nx))
    u_p = ocp.parameter("u_p", system.nu)
    ocp.dynamics()
    ocp.input_constraint(U)
    ocp.state_constraint(X)
    ocp.terminal_constraint(Xf)
    ocp.minimize(squared_norm(ocp.u[:, 0] - u_p, label="filter"))
    return ocp


def cbf_filter_problem(system: System, U: Set, h: Callable, decrease: Callable | float,
                       name: str = "cbf_filter") -> OCP:
    """(2.20): ``min_u ‖u − u_p‖²`` s.t. ``u ∈ U`` and ``h(f(x, u)) − h(x) <= −α(x)``.

    ``decrease`` is ``α(x)`` as a function of the state (e.g. ``α₃(‖x‖_S)``) or a constant.
    Parameters: ``x``, ``u_p``; variable ``u``. For a quadratic ``h`` and linear ``f`` the
    problem is a convex QCQP and compiles on both backends.
    """
    check_system_sets(name, system, U=U)
    check_callable(h, f"{name}: h")
    if not callable(decrease):
        # α₃ ∈ K in (2.20) (SPEC §2.6, Def. 2.26): α >= 0; a negative constant lets h grow
        decrease = as_scalar(decrease, f"{name}: decrease (constant α in (2.20), >= 0)",
                             low=0.0)
    ocp = OCP(name=name)
    x = ocp.parameter("x", system.nx)
    u_p = ocp.parameter("u_p", system.nu)
    u = ocp.variable("u", system.nu, role="input")
    ocp.le(U.c(u), 0, name="input", tag="input")
    try:
        alpha = decrease(x) if callable(decrease) else float(decrease)
        lhs = h(system(x, u)) - h(x) + alpha
    except Exception as exc:  # the user's functions failed on symbols
        raise BalustradeError(f"{name}: h(f(x, u)) − h(x) + α(x) failed on CasADi symbols "
                              f"x ({system.nx}, 1), u ({system.nu}, 1): {exc}") from exc
    ocp.decrease(lhs, 0, name="cbf_decrease")
    ocp.minimize(squared_norm(u - u_p, label="filter"))
    return ocp
