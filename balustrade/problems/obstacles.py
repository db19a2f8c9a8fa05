"""Formulations of thesis Section 8.3 (SPEC §2.32): the PCBF of the obstacle car with a
hard terminal constraint, its extended form, and the obstacle-unaware naive MPC (8.2).

* :func:`stopping_pcbf_problem` — (2.24) with ``ξ_N ≡ 0``: ``min Σ_i ‖ξ_i‖`` s.t.
  ``x_0 = x_k``, (8.1), ``u_i ∈ U``, ``c_x(x_i) + Δ_i 1 <= ξ_i``, ``ξ_i >= 0`` and the hard
  terminal constraint ``v_N = 0``, ``c_x(x_N) + Δ_N 1 <= 0`` (SPEC §2.32 reads the printed
  "``c_x(x) − Δ_N <= 0``" as a sign typo). There is no ``α_f`` term; (2.24) is infeasible
  where no input sequence stops the car outside the tightened obstacles within ``N`` steps.
* :func:`stopping_extended_problem` — (7.8) in epigraph form with the same hard terminal
  constraint: ``min t`` s.t. ``c_x(x_i) + Δ_i 1 <= t 1`` for ``i < N``.
* :func:`stopping_filter_problem` — (2.23) for it: ``min ‖u_0 − u_p‖²`` with the slacks
  fixed to the optimum of :func:`stopping_pcbf_problem` (the PCBF algorithm [41] that
  Section 8.3 compares with, via :class:`~balustrade.control.pcbf.PCBFSafetyFilter`).
* :func:`naive_mpc_problem` — (8.2): ``min Σ_{i=0}^{M} ‖p_i + p_0‖² + (v_i − v_ref)²`` over
  ``M = 30`` steps, inputs in ``U``, no state constraint; parameters ``x0`` and ``p0`` (the
  episode's initial position, so the target ``−p_0`` is the reflected start).
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from balustrade._checks import as_scalar, check_deltas, check_horizon, check_norm_order
from balustrade.dsl import OCP, Set, System, squared_norm, sum_norms
from balustrade.problems._args import check_system_sets


def _common(name: str, system: System, X: Set, U: Set, N: int, deltas: object,
            delta_N: float, speed_index: int) -> tuple[OCP, np.ndarray, float]:
    check_system_sets(name, system, X, U)
    N = check_horizon(N, name)
    deltas = check_deltas(deltas, N, name)
    delta_N = as_scalar(delta_N, f"{name}: delta_N", 0.0)
    if not 0 <= int(speed_index) < system.nx:
        from balustrade.errors import BalustradeError

        raise BalustradeError(f"{name}: speed_index must be in [0, {system.nx}), got "
                              f"{speed_index!r}")
    ocp = OCP(system, N, name=name)
    ocp.initial_state(ocp.parameter("x0", system.nx))
    ocp.dynamics()
    ocp.input_constraint(U)
    ocp.eq(ocp.x[int(speed_index), N], 0.0, name="terminal_stop", tag="terminal")
    ocp.terminal_constraint(X, tightening=delta_N)
    return ocp, deltas, delta_N


def stopping_pcbf_problem(system: System, X: Set, U: Set, N: int, deltas: object,
                          delta_N: float, speed_index: int = 3,
                          slack_norm: int | float | str = "inf",
                          name: str = "pcbf_stop") -> OCP:
    """(2.24) with the hard terminal constraint of Section 8.3 (module docstring).

    Parameters: ``x0``. The objective is ``h_PB(x_k) = Σ_i ‖ξ_i‖``. ``slack_norm="inf"``
    (default): ``‖ξ_i‖_∞`` written exactly as one scalar slack ``s_i >= 0`` per step with
    ``c_x(x_i) + Δ_i 1 <= s_i 1`` (variable ``xi`` of shape ``(1, N)``; ``Σ_i s_i`` is
    minimized, and at the optimum ``s_i = max_j (c_{x,j}(x_i) + Δ_i)^+``). That is N slacks
    instead of N × 11 and about half the solve time; SPEC §1.12: any norm keeps the theory.
    ``slack_norm`` 1 or 2: one slack per row and step (variable ``xi`` of shape
    ``(rows of c_x, N)``)."""
    check_norm_order(slack_norm, f"{name}: slack_norm")
    ocp, deltas, _ = _common(name, system, X, U, N, deltas, delta_N, speed_index)
    # ξ_N ≡ 0: a terminal slack fixed to zero, so the PCBF algorithm's interface (xi, xi_N)
    # holds; the terminal constraint itself is hard
    ocp.variable("xi_N", 1, lb=0.0, ub=0.0, role="slack")
    if slack_norm in (np.inf, "inf"):
        s = ocp.variable("xi", 1, ocp.N, lb=0.0, role="slack")
        ocp.state_constraint(X, tightening=deltas, slack=ca.repmat(s, X.n_rows, 1))
        ocp.minimize(ca.sum2(s))
        return ocp
    xi = ocp.state_constraint(X, tightening=deltas,
                              slack=ocp.variable("xi", X.n_rows, ocp.N, lb=0.0, role="slack"))
    ocp.minimize(sum_norms(xi, slack_norm, label="slack"))
    return ocp


def stopping_extended_problem(system: System, X: Set, U: Set, N: int, deltas: object,
                              delta_N: float, speed_index: int = 3,
                              name: str = "pcbf_stop_extended") -> OCP:
    """(7.8) with the hard terminal constraint: ``h̄_PB(x_k) = min t`` s.t.
    ``c_x(x_i) + Δ_i 1 <= t 1`` (``i < N``), dynamics, ``u_i ∈ U``, ``v_N = 0``,
    ``c_x(x_N) + Δ_N 1 <= 0``. Parameter: ``x0``; variable ``t``."""
    ocp, deltas, _ = _common(name, system, X, U, N, deltas, delta_N, speed_index)
    t = ocp.variable("t", 1, role="slack")
    ocp.state_constraint(X, tightening=deltas, slack=t)
    ocp.minimize(t)
    return ocp


def stopping_filter_problem(system: System, X: Set, U: Set, N: int, deltas: object,
                            delta_N: float, speed_index: int = 3, slack_rows: int = 1,
                            eps: float = 1e-6, name: str = "pcbf_stop_filter") -> OCP:
    """(2.23) for :func:`stopping_pcbf_problem`: ``min ‖u_0 − u_p‖²`` s.t. its constraints
    with ``c_x(x_i) + Δ_i 1 <= ξ*_i + eps`` and the hard terminal constraint.

    Parameters: ``x0``, ``u_p``, ``xi`` (``(slack_rows, N)``: 1 for the ∞-norm slack, the
    rows of ``c_x`` otherwise) and ``xi_N`` (unused: ``ξ_N ≡ 0``)."""
    eps = as_scalar(eps, f"{name}: eps", 0.0)
    ocp, deltas, _ = _common(name, system, X, U, N, deltas, delta_N, speed_index)
    u_p = ocp.parameter("u_p", system.nu)
    xi = ocp.parameter("xi", int(slack_rows), ocp.N, lb=0.0)   # slacks ξ >= 0 (SPEC §1.4)
    ocp.parameter("xi_N", 1, lb=0.0)
    rows = ca.repmat(xi, X.n_rows // int(slack_rows), 1) if slack_rows == 1 else xi
    ocp.state_constraint(X, tightening=deltas, slack=rows + eps)
    ocp.minimize(squared_norm(ocp.u[:, 0] - u_p, label="filter"))
    return ocp


def _state_indices(position: object, speed_index: object, nx: int, name: str
                   ) -> tuple[int, int]:
    """``position`` (two state indices) and ``speed_index``, each an integer in
    ``[0, nx)``, else a BalustradeError naming it (an index past the state used to end in a
    CasADi slice assertion; audit D, session 15)."""
    from balustrade._checks import as_count
    from balustrade.errors import BalustradeError

    if isinstance(position, (str, bytes)) or np.ndim(position) != 1 or len(position) != 2:
        raise BalustradeError(f"{name}: position must be two state indices (p_x, p_y), got "
                              f"{position!r:.40}")
    for label, i in (("position[0]", position[0]), ("position[1]", position[1]),
                     ("speed_index", speed_index)):
        if as_count(i, f"{name}: {label}") >= nx:
            raise BalustradeError(f"{name}: {label} must be in [0, {nx}), got {i!r}")
    return int(position[0]), int(position[1])


def naive_mpc_problem(system: System, U: Set, horizon: int = 30, v_ref: float = 3.0,
                      position: tuple[int, int] = (0, 1), speed_index: int = 3,
                      name: str = "naive_mpc") -> OCP:
    """(8.2): ``Σ_{i=0}^{M} ‖p_{x,i} + p_{x,0}‖² + ‖p_{y,i} + p_{y,0}‖² + ‖v_i − v_ref‖²`` with
    ``M = horizon`` (inputs ``u_0 … u_{M−1}`` in ``U``), no state constraint.

    Parameters: ``x0`` (the state) and ``p0`` (the episode's initial position)."""
    check_system_sets(name, system, U=U)
    M = check_horizon(horizon, name)
    v_ref = as_scalar(v_ref, f"{name}: v_ref")
    ocp = OCP(system, M, name=name)
    ocp.initial_state(ocp.parameter("x0", system.nx))
    ix, iy = _state_indices(position, speed_index, system.nx, name)
    p0 = ocp.parameter("p0", 2)
    ocp.dynamics()
    ocp.input_constraint(U)
    cost = ca.SX(0)
    for i in range(M + 1):
        xi = ocp.x[:, i]
        cost += (xi[ix] + p0[0]) ** 2 + (xi[iy] + p0[1]) ** 2 + (xi[speed_index] - v_ref) ** 2
    ocp.minimize(cost)
    return ocp


__all__ = ["naive_mpc_problem", "stopping_extended_problem", "stopping_filter_problem",
           "stopping_pcbf_problem"]
