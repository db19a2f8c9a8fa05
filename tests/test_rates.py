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


# -- closed loop: the controller passes the input it applied last as u_prev -------------------
def closed_loop_problem(rate: float = 0.2):
    import casadi as ca

    from balustrade.control import ContinuousPlant

    plant = ContinuousPlant(lambda x, u: ca.vertcat(x[1], u[0]), nx=2, nu=1, dt=0.1)
    ocp = OCP(plant.discretize("rk4"), N=20, name="rate_loop")
    ocp.initial_state(ocp.parameter("x0", 2))
    ocp.dynamics()
    ocp.input_constraint(Box.symmetric([1.0]))
    ocp.rate_limit(rate)
    ocp.minimize(ocp.tracking_cost(Q=[10.0, 1.0], R=0.01, P=[100.0, 10.0]) + ocp.rate_cost(1.0))
    return plant, ocp


def test_closed_loop_rate_limit_holds_from_the_applied_inputs():
    from balustrade.control import MPCController, simulate

    plant, ocp = closed_loop_problem()
    u_init = np.array([0.5])
    ctl = MPCController(compile(ocp, "cvxpy"), parameters=lambda k, x: {
        "x_ref": [1.0 if k < 30 else -0.5, 0.0]}, u_init=u_init)
    trace = simulate(plant, ctl, [0.0, 0.0], 60)
    assert trace.stopped is None and trace.n_fallbacks == 0
    du = np.diff(np.concatenate([u_init, trace.inputs[:, 0]]))
    assert np.max(np.abs(du)) <= 0.2 + 1e-7
    assert np.max(np.abs(du)) >= 0.2 - 1e-6  # the limit is active somewhere
    assert trace.states[30, 0] == pytest.approx(1.0, abs=0.05)  # tracks the first reference
    assert trace.states[-1, 0] == pytest.approx(-0.5, abs=0.05)  # and the second
    assert "objective" in trace.values
    # reset() starts again from u_init: the same run twice
    ctl.reset()
    again = simulate(plant, ctl, [0.0, 0.0], 5)
    np.testing.assert_allclose(again.inputs, trace.inputs[:5], atol=1e-8)


def test_mpc_controller_falls_back_on_failed_solves():
    from balustrade.control import MPCController

    _, ocp = closed_loop_problem()
    real = compile(ocp, "cvxpy")

    class Flaky:
        def __init__(self):
            self.ocp, self.calls, self.seen = ocp, 0, []

        def solve(self, params, warm_start=None):
            self.calls += 1
            self.seen.append(np.array(params["u_prev"]))
            sol = real.solve(params)
            return sol if self.calls == 1 else type(sol)(**{**sol.__dict__, "status": "failed"})

    flaky = Flaky()
    ctl = MPCController(flaky, parameters={"x_ref": [1.0, 0.0]})
    plan = real.solve({"x0": [0.0, 0.0], "u_prev": [0.0], "x_ref": [1.0, 0.0]})["u"][0]
    applied = []
    for k in range(23):
        u, info = ctl.step(np.zeros(2), None)
        applied.append(u[0])
        expected = None if k == 0 else ("shifted_plan" if k < 20 else "hold")
        assert info.fallback == expected, (k, info.fallback)
        assert k == 0 or info.uncertified == {"mpc": "failed"}
    np.testing.assert_allclose(applied[:20], plan, atol=1e-9)  # the plan, shifted
    assert applied[20:] == [applied[19]] * 3  # then the last input, held
    np.testing.assert_allclose(np.concatenate(flaky.seen[1:4]), applied[:3])  # u_prev
    u, info = ctl.step(np.array([np.nan, 0.0]), None)
    assert info.status == "non_finite_state" and info.fallback == "hold"
    with pytest.raises(BalustradeError, match="no initial-state parameter 'x_0'"):
        MPCController(real, state="x_0")
    with pytest.raises(BalustradeError, match=r"parameters\(k, x\) failed at step 0"):
        MPCController(real, parameters=lambda k, x: 1 / 0).step(np.zeros(2))
