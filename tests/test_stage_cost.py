"""The one quadratic stage/trajectory cost helper: the expression a formulation minimizes
and the number an algorithm evaluates are the same formula."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from balustrade.problems._costs import stage_cost, trajectory_cost


def test_symbolic_and_numeric_costs_agree():
    rng = np.random.default_rng(0)
    n, m, M = 3, 2, 4
    A = rng.standard_normal((n, n))
    Q, R, P = A @ A.T, np.diag([1.0, 2.0]), np.eye(n) * 3.0
    x, u = rng.standard_normal((n, M + 1)), rng.standard_normal((m, M))
    X, U = ca.SX.sym("x", n, M + 1), ca.SX.sym("u", m, M)
    f = ca.Function("J", [X, U], [trajectory_cost(X, U, Q, R, P)])
    expected = sum(x[:, i] @ Q @ x[:, i] + u[:, i] @ R @ u[:, i] for i in range(M)) \
        + x[:, M] @ P @ x[:, M]
    assert float(f(x, u)) == pytest.approx(expected, rel=1e-13)
    assert trajectory_cost(x, u, Q, R, P) == pytest.approx(expected, rel=1e-13)
    assert stage_cost(x[:, 0], u[:, 0], Q, R) == pytest.approx(
        x[:, 0] @ Q @ x[:, 0] + u[:, 0] @ R @ u[:, 0], rel=1e-13)


def test_mpc_and_the_lyapunov_design_use_it():
    from balustrade.dsl.sets import Box
    from balustrade.dsl.system import LinearSystem
    from balustrade.problems.mpc import mpc_problem
    from balustrade.problems.multiobjective import LinearLyapunovDesign

    sysm = LinearSystem(np.array([[1.0, 0.1], [0.0, 1.0]]), np.array([[0.0], [0.1]]))
    X, U = Box.symmetric([5.0, 5.0]), Box.symmetric([1.0])
    Q, R, P = np.eye(2), np.eye(1), 2 * np.eye(2)
    ocp = mpc_problem(sysm, X, U, None, 3, Q, R, P)
    z = np.column_stack([[1.0, 0.5], [0.2, -0.1], [0.0, 0.3], [0.4, 0.4]])
    v = np.array([[0.1, -0.2, 0.3]])
    value = sum(t.value_expr() for t in ocp.cost.terms)
    obj = ca.Function("J", [ocp.x, ocp.u], [value])
    assert float(obj(z, v)) == pytest.approx(trajectory_cost(z, v, Q, R, P), rel=1e-13)
    d = LinearLyapunovDesign(sysm, X, U, X, Box.symmetric([0.01, 0.01]),
                             np.array([[-1.0, -1.5]]), Q, R, 3)
    x0 = np.array([0.3, -0.2])
    z = d.rollout(x0, v)  # (6.2) written out: ½ Σ_i (z_iᵀQz_i + v_iᵀRv_i) + ½ z_NᵀPz_N
    expected = 0.5 * sum(z[:, i] @ Q @ z[:, i] + v[:, i] @ R @ v[:, i] for i in range(3)) \
        + 0.5 * z[:, 3] @ d.P @ z[:, 3]
    assert d.V(x0, v) == pytest.approx(expected, rel=1e-13)
