"""Reference-tracking stage costs with the reference as a parameter (constant or a
trajectory over the horizon), on both backends (issue #13 §7)."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from balustrade.backends import compile
from balustrade.dsl import OCP, Box, LinearSystem, tracking_cost
from balustrade.errors import BalustradeError, NotPSDError, ShapeError
from balustrade.testing import verify

N = 10


def tracking_ocp(trajectory: bool, u_ref: object = "u_ref") -> OCP:
    sys_ = LinearSystem([[1.0, 0.1], [0.0, 1.0]], [[0.005], [0.1]], name="di")
    ocp = OCP(sys_, N=N, name="track")
    ocp.initial_state(ocp.parameter("x0", 2))
    ocp.dynamics()
    ocp.input_constraint(Box.symmetric([3.0]))
    ocp.minimize(ocp.tracking_cost(Q=np.diag([5.0, 0.5]), R=0.1, P=[20.0, 2.0], u_ref=u_ref,
                                   trajectory=trajectory))
    return ocp


def agree(ocp: OCP, params: dict) -> dict:
    sols = {t: compile(ocp, t).solve(params) for t in ("casadi", "cvxpy")}
    assert all(s.success for s in sols.values()), {t: s.summary() for t, s in sols.items()}
    a, b = sols["casadi"].objective, sols["cvxpy"].objective
    assert abs(a - b) <= 1e-6 * max(1.0, abs(a)), (a, b)
    np.testing.assert_allclose(sols["casadi"]["x"], sols["cvxpy"]["x"], atol=1e-5)
    for s in sols.values():
        assert verify(ocp, s).ok
    return sols


def test_constant_reference_on_both_backends():
    ocp = tracking_ocp(False)
    assert ocp.parameters["x_ref"].shape == (2, 1) and ocp.parameters["u_ref"].shape == (1, 1)
    sols = agree(ocp, {"x0": [0.0, 0.0], "x_ref": [1.0, 0.0], "u_ref": [0.0]})
    x = sols["cvxpy"]["x"]
    assert x[0, -1] > 0.5  # moves towards the reference
    # at the reference with zero input the cost is zero and the plan stays put
    rest = agree(ocp, {"x0": [1.0, 0.0], "x_ref": [1.0, 0.0], "u_ref": [0.0]})
    assert rest["cvxpy"].objective == pytest.approx(0.0, abs=1e-8)
    np.testing.assert_allclose(rest["cvxpy"]["u"], 0.0, atol=1e-6)


def test_trajectory_reference_on_both_backends():
    ocp = tracking_ocp(True)
    assert ocp.parameters["x_ref"].shape == (2, N + 1)
    assert ocp.parameters["u_ref"].shape == (1, N)
    t = np.arange(N + 1) * 0.1
    ref = np.vstack([np.sin(t), np.cos(t)])
    sols = agree(ocp, {"x0": [0.0, 1.0], "x_ref": ref, "u_ref": -np.sin(t[:N])[None, :] * 10})
    # the cost is the declared one: evaluate it by hand at the solution
    s = sols["casadi"]
    x, u = s["x"], s["u"]
    e = x - ref
    by_hand = (sum(e[:, i] @ np.diag([5.0, 0.5]) @ e[:, i] for i in range(N))
               + e[:, N] @ np.diag([20.0, 2.0]) @ e[:, N]
               + 0.1 * np.sum((u + np.sin(t[:N]) * 10) ** 2))
    assert s.objective == pytest.approx(by_hand, rel=1e-9)


def test_reference_kinds():
    """A numeric reference, an expression and None (regulate to the origin)."""
    ocp = tracking_ocp(False, u_ref=None)
    assert "u_ref" not in ocp.parameters
    sys_ = ocp.system
    fixed = OCP(sys_, N=3, name="fixed")
    cost = tracking_cost(fixed, Q=1.0, x_ref=np.array([1.0, 2.0]))
    f = ca.Function("c", [fixed.x], [cost.expr()])
    assert float(f(np.zeros((2, 4)))) == pytest.approx(3 * 5.0)
    expr = OCP(sys_, N=3, name="expr")
    target = expr.parameter("target", 1)
    cost = tracking_cost(expr, Q=[1.0, 0.0], x_ref=ca.vertcat(target, 0))
    assert "x_ref" not in expr.parameters
    f = ca.Function("c", [expr.x, target], [cost.expr()])
    assert float(f(np.ones((2, 4)), 3.0)) == pytest.approx(3 * 4.0)


def test_tracking_errors_name_the_thing():
    ocp = tracking_ocp(False)
    with pytest.raises(NotPSDError, match="Q"):
        ocp.tracking_cost(Q=[[1.0, 0.0], [0.0, -1.0]])
    with pytest.raises(ShapeError, match="R"):
        ocp.tracking_cost(R=[1.0, 2.0])
    with pytest.raises(BalustradeError, match="at least one of Q, R, P"):
        ocp.tracking_cost()
    with pytest.raises(ShapeError, match="x_ref"):
        ocp.tracking_cost(Q=1.0, x_ref=np.ones(3))
    ocp.parameter("short", 2, 5)  # neither (2, 1) nor a (2, N+1) trajectory
    with pytest.raises(ShapeError, match="reference 'short'"):
        ocp.tracking_cost(Q=1.0, x_ref="short", trajectory=True)
