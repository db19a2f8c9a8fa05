"""Rate limits and rate costs on Δu_i = u_i − u_{i−1}, u_{−1} = u_prev (issue #13 §7): both
backends agree, solutions satisfy the declared limits (checked by verify and by hand)."""

from __future__ import annotations

import numpy as np
import pytest

from balustrade.backends import compile
from balustrade.dsl import OCP, Box, LinearSystem, input_rates, rate_cost, rate_limit, sum_norms
from balustrade.errors import BalustradeError, NonFiniteError, ShapeError
from balustrade.testing import verify

RATE = 0.3


def double_integrator() -> LinearSystem:
    return LinearSystem([[1.0, 0.1], [0.0, 1.0]], [[0.005], [0.1]], name="di")


def rate_mpc(soft: bool, R: float = 0.5, N: int = 12) -> tuple[OCP, object]:
    ocp = OCP(double_integrator(), N=N, name=f"rate_{'soft' if soft else 'hard'}")
    x0 = ocp.parameter("x0", 2)
    ocp.initial_state(x0)
    ocp.dynamics()
    ocp.input_constraint(Box.symmetric([2.0]))
    xi = ocp.rate_limit(RATE, soft=soft)
    cost = ocp.tracking_cost(Q=[10.0, 1.0], R=0.01, P=[10.0, 1.0]) + ocp.rate_cost(R)
    ocp.minimize(cost + 50.0 * sum_norms(xi, 1) if soft else cost)
    return ocp, xi


PARAMS = [{"x0": [0.0, 0.0], "u_prev": [0.0], "x_ref": [1.0, 0.0]},
          {"x0": [0.5, -1.0], "u_prev": [1.5], "x_ref": [-1.0, 0.0]},
          {"x0": [2.0, 0.5], "u_prev": [-0.7], "x_ref": [0.0, 0.0]}]


@pytest.mark.parametrize("soft", [False, True])
def test_rate_limited_mpc_backends_agree_and_verify(soft):
    ocp, _ = rate_mpc(soft)
    compiled = {t: compile(ocp, t) for t in ("casadi", "cvxpy")}
    for params in PARAMS:
        sols = {t: c.solve(params) for t, c in compiled.items()}
        assert all(s.success for s in sols.values()), {t: s.summary() for t, s in sols.items()}
        a, b = sols["casadi"].objective, sols["cvxpy"].objective
        assert abs(a - b) <= 1e-6 * max(1.0, abs(a)), (params, a, b)
        np.testing.assert_allclose(sols["casadi"]["u"], sols["cvxpy"]["u"], atol=1e-5)
        for s in sols.values():
            report = verify(ocp, s, tol=1e-6)
            assert report.ok, str(report)
            assert report.block_violation["rate"] <= 1e-6
            du = np.diff(np.concatenate([params["u_prev"], s["u"][0]]))
            if soft:
                assert np.all(np.abs(du) <= RATE + s["xi_rate"][0] + 1e-6)
            else:
                assert np.all(np.abs(du) <= RATE + 1e-6)


def test_hard_limit_binds_and_soft_limit_uses_its_slack():
    """From u_prev = 1.5 to a target needing negative input, the hard limit allows
    at most 0.3 per step; the soft one with a cheap slack moves faster, paying ξ."""
    params = PARAMS[1]
    hard, _ = rate_mpc(False)
    s = compile(hard, "cvxpy").solve(params)
    du = np.diff(np.concatenate([[1.5], s["u"][0]]))
    assert np.max(np.abs(du)) == pytest.approx(RATE, abs=1e-6)  # the limit is active
    soft, xi = rate_mpc(True)
    soft.minimize(soft.tracking_cost(Q=[10.0, 1.0], R=0.01, P=[10.0, 1.0])
                  + soft.rate_cost(0.5) + 0.01 * sum_norms(xi, 1))
    s2 = compile(soft, "cvxpy").solve(params)
    assert s2.success and np.max(s2["xi_rate"]) > 1e-3
    assert verify(soft, s2).ok
    # a point breaking the hard limit is caught by verify
    broken = type(s)(**{**s.__dict__})
    broken.primal["u"] = s["u"].copy()
    broken.primal["u"][0, 0] = 1.5 - 2 * RATE
    report = verify(hard, broken)
    assert report.block_violation["rate"] == pytest.approx(RATE, abs=1e-9)


def test_rate_cost_value_and_u_prev_shared():
    ocp = OCP(double_integrator(), N=4, name="r")
    du = input_rates(ocp)
    assert du.shape == (1, 4)
    rate_limit(ocp, 1.0)
    cost = rate_cost(ocp, 2.0)
    assert list(ocp.parameters) == ["u_prev"]  # one previous-input parameter for both
    import casadi as ca

    f = ca.Function("c", [ocp.u, ocp.parameters["u_prev"].sym], [cost.expr()])
    u = np.array([[1.0, 3.0, 2.0, 2.0]])
    assert float(f(u, 0.5)) == pytest.approx(2.0 * (0.5**2 + 2.0**2 + 1.0**2 + 0.0))


def test_rate_cost_penalizes_moves_on_both_backends():
    """A large rate cost makes the plan smoother: Σ Δu² decreases with R, equally on both."""
    moves = {}
    for R in (0.0, 10.0):
        ocp, _ = rate_mpc(False, R=R)
        sols = [compile(ocp, t).solve(PARAMS[0]) for t in ("casadi", "cvxpy")]
        assert abs(sols[0].objective - sols[1].objective) <= 1e-6 * max(1, sols[0].objective)
        moves[R] = float(np.sum(np.diff(np.concatenate([[0.0], sols[1]["u"][0]])) ** 2))
    assert moves[10.0] < moves[0.0]


def test_rate_errors_name_the_thing():
    ocp = OCP(double_integrator(), N=3, name="bad")
    with pytest.raises(BalustradeError, match="rate limit must be >= 0"):
        ocp.rate_limit(-1.0)
    with pytest.raises(NonFiniteError, match="rate"):
        ocp.rate_limit(np.nan)
    with pytest.raises(ShapeError):
        ocp.rate_limit([1.0, 2.0])
    ocp.parameter("u_prev", 2)
    with pytest.raises(ShapeError, match="u_prev"):
        ocp.rate_limit(1.0)
    with pytest.raises(BalustradeError, match="needs an OCP built with a system"):
        rate_limit(OCP(name="empty"), 1.0)
