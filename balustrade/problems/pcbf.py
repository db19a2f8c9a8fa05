"""The predictive control barrier function family (thesis Sections 2.4 and 7.3).

* :func:`pcbf_slack_problem` — (2.24): ``h_PB(x_k)``, the minimal weighted slack;
* :func:`pcbf_filter_problem` — (2.23): the safety filter with the slacks fixed to the
  optimum of (2.24);
* :func:`extended_pcbf_problem` — (7.8): ``h̄_PB(x_k)``, the largest signed slack (epigraph
  form), negative strictly inside ``S_PB``;
* :func:`combined_h` — (7.7)/(7.9): ``h = h_PB`` outside ``S_PB``, ``c_h · h̄_PB`` on it.

Each builder is a few lines of the language; the slack norm ``‖ξ_i‖`` is configurable
(SPEC §1.12: any norm preserves the theory; ``1`` keeps linear examples LP/QP-like).
"""

from __future__ import annotations

from collections.abc import Callable

import casadi as ca
import numpy as np

from balustrade._checks import as_scalar
from balustrade.dsl import OCP, Set, System, squared_norm, sum_norms
from balustrade.problems._args import check_norm_order, check_pcbf_args, nonnegative, positive


def pcbf_slack_problem(system: System, X: Set, U: Set, h_f: Callable, N: int,
                       deltas: np.ndarray, alpha_f: float = 1e6, slack_norm: int | float = 2,
                       name: str = "pcbf_slack") -> OCP:
    """(2.24): ``min α_f ξ_N + Σ_i ‖ξ_i‖`` s.t. ``x_0 = x_k``, dynamics, ``u_i ∈ U``,
    ``c_x(x_i) + Δ_i 1 <= ξ_i``, ``ξ_i >= 0``, ``h_f(x_N) <= ξ_N``, ``ξ_N >= 0``.

    Parameters: ``x0``. Variables: ``x``, ``u``, ``xi`` (rows of ``c_x`` × N), ``xi_N``.
    """
    N, deltas = check_pcbf_args(name, system, X, U, h_f, N, deltas)
    alpha_f = positive(alpha_f, f"{name}: alpha_f")
    check_norm_order(slack_norm, f"{name}: slack_norm")
    ocp = OCP(system, N, name=name)
    ocp.initial_state(ocp.parameter("x0", system.nx))
    ocp.dynamics()
    ocp.input_constraint(U)
    xi = ocp.state_constraint(X, tightening=deltas, slack=_named(ocp, "xi", X.n_rows, N))
    xi_N = ocp.terminal_cbf(h_f, slack=_named(ocp, "xi_N", 1, 1))
    ocp.minimize(alpha_f * xi_N + sum_norms(xi, slack_norm, label="slack"))
    return ocp


def pcbf_filter_problem(system: System, X: Set, U: Set, h_f: Callable, N: int,
                        deltas: np.ndarray, eps: float = 1e-6,
                        name: str = "pcbf_filter") -> OCP:
    """(2.23): ``min ‖u_0 − u_p‖²`` s.t. the constraints of (2.24) with the slacks fixed to
    the parameters ``xi``, ``xi_N`` (the optimum of (2.24)) plus the numerical margin ``eps``
    (SPEC §2.7 implementation notes). Parameters: ``x0``, ``u_p``, ``xi``, ``xi_N``."""
    N, deltas = check_pcbf_args(name, system, X, U, h_f, N, deltas)
    eps = nonnegative(eps, f"{name}: eps")
    ocp = OCP(system, N, name=name)
    ocp.initial_state(ocp.parameter("x0", system.nx))
    u_p = ocp.parameter("u_p", system.nu)
    # ξ >= 0 (2.24): a negative slack would tighten X past Δ_i and the filter would
    # answer a problem the PCBF theory does not cover; refused when the values are packed
    xi = ocp.parameter("xi", X.n_rows, N, lb=0.0)
    xi_N = ocp.parameter("xi_N", 1, lb=0.0)
    ocp.dynamics()
    ocp.input_constraint(U)
    ocp.state_constraint(X, tightening=deltas, slack=xi + eps)
    ocp.terminal_cbf(h_f, slack=xi_N + eps)
    ocp.minimize(squared_norm(ocp.u[:, 0] - u_p, label="filter"))
    return ocp


def extended_pcbf_problem(system: System, X: Set, U: Set, h_f: Callable, N: int,
                          deltas: np.ndarray, name: str = "pcbf_extended") -> OCP:
    """(7.8) in epigraph form (SPEC §2.29): ``min t`` s.t. ``c_x(x_i) + Δ_i 1 <= t 1``,
    ``h_f(x_N) <= t`` and (2.24b–d). The signed slacks of (7.8) are all equal to the
    epigraph variable ``t``; a per-row signed slack (``state_constraint(signed=True)``)
    gives the same value but a degenerate problem. Parameter: ``x0``; variable ``t``."""
    N, deltas = check_pcbf_args(name, system, X, U, h_f, N, deltas)
    ocp = OCP(system, N, name=name)
    ocp.initial_state(ocp.parameter("x0", system.nx))
    ocp.dynamics()
    ocp.input_constraint(U)
    t = ocp.variable("t", 1, role="slack")
    ocp.state_constraint(X, tightening=deltas, slack=t)
    ocp.terminal_cbf(h_f, slack=t)
    ocp.minimize(t)
    return ocp


def combined_h(h_pb: float, h_bar: float, c_h: float = 1.0, tol: float = 1e-6) -> float:
    """(7.7)/(7.9): ``h = h_PB`` on ``D_PB \\ S_PB`` and ``c_h · h̄_PB`` on ``S_PB``;
    ``S_PB = {h_PB <= tol}`` numerically."""
    h_pb, h_bar = as_scalar(h_pb, "combined_h: h_pb"), as_scalar(h_bar, "combined_h: h_bar")
    c_h = positive(c_h, "combined_h: c_h")
    tol = nonnegative(tol, "combined_h: tol")
    return c_h * h_bar if h_pb <= tol else h_pb


def _named(ocp: OCP, name: str, rows: int, cols: int, signed: bool = False) -> ca.SX:
    return ocp.variable(name, rows, cols, lb=-np.inf if signed else 0.0, role="slack")
