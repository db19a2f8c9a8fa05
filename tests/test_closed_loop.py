"""The PCBF safety filter in closed loop on the pendulum (Figure 7.1 PCBF curves) and its
fallbacks."""

from __future__ import annotations

import numpy as np
import pytest

from balustrade.backends import Solution
from balustrade.control import PCBFSafetyFilter, simulate
from balustrade.errors import BalustradeError
from balustrade.testing import verify

INITIAL_RATES = (-1.5, -0.75, 0.0, 0.75, 1.5)


@pytest.fixture(scope="module")
def controller(pend) -> PCBFSafetyFilter:
    return PCBFSafetyFilter(pend.compiled["slack", "casadi"], pend.compiled["filter", "casadi"],
                            pend.U)


@pytest.mark.parametrize("omega0", INITIAL_RATES)
def test_pendulum_runs_are_safe_and_verified(pend, controller, omega0):
    controller.reset()
    trace = simulate(pend.system, controller, [0.0, omega0], 150, proposal=2.0,
                     keep_infos=True)
    assert trace.stopped is None and len(trace.states) == 151
    h = trace.values["h_PB"]
    inside = np.flatnonzero(h <= 1e-6)
    assert inside.size, "the run must reach S_PB"
    after = trace.states[inside[0]:]
    assert np.max(after[:, 0]) <= 0.5 + 1e-6  # ψ <= 0.5 once inside S_PB
    assert np.max(np.abs(after[:, 1])) <= 1.5 + 1e-6
    assert np.all(np.abs(trace.inputs) <= 3.0 + 1e-9)
    assert trace.states[-1, 0] == pytest.approx(0.5 - pend.deltas[1], abs=5e-3)
    for info in trace.infos:
        for name, sol in info.solutions.items():
            ocp = pend.slack if name == "slack" else pend.filter
            report = verify(ocp, sol, tol=1e-6)
            assert report.ok, str(report)


def test_filter_passes_safe_proposals_unchanged(pend, controller):
    controller.reset()
    u, info = controller.step(np.array([0.0, 0.0]), np.array([0.3]))
    assert info.fallback is None and u[0] == pytest.approx(0.3, abs=1e-7)


class _Failing:
    """A compiled problem whose solver always fails (to exercise the fallbacks)."""

    def __init__(self, ocp):
        self.ocp = ocp

    def solve(self, params=None, warm_start=None) -> Solution:
        n = self.ocp.decision_vector().numel()
        w = np.full(n, np.nan)
        return Solution("failed", np.nan, self.ocp.unpack_variables(w), {}, 0.0, 0, "test",
                        "failing", w, self.ocp.pack_parameters(params))


def test_failed_solves_fall_back_without_raising(pend):
    ctl = PCBFSafetyFilter(pend.compiled["slack", "casadi"], _Failing(pend.filter), pend.U)
    trace = simulate(pend.system, ctl, [0.0, 1.0], 5, proposal=2.0)
    assert trace.fallbacks == ["slack_solution"] * 5
    # step 0 solves (2.24) (no plan yet); later steps skip it on the shifted plan of the
    # (2.24) solution applied (certificate first, the default): "certified_filter_failed"
    assert trace.statuses[0].startswith("filter_failed")
    assert all(s.removeprefix("certified_").startswith("filter_failed")
               for s in trace.statuses)

    good = PCBFSafetyFilter(pend.compiled["slack", "casadi"], pend.compiled["filter", "casadi"],
                            pend.U)
    good.step(np.array([0.0, 1.0]), np.array([2.0]))  # one successful plan
    good.slack = _Failing(pend.slack)
    u, info = good.step(np.array([0.05, 1.0]), np.array([2.0]))
    assert info.fallback == "shifted_plan" and np.all(np.isfinite(u))
    ctl = PCBFSafetyFilter(_Failing(pend.slack), pend.compiled["filter", "casadi"], pend.U)
    trace = simulate(pend.system, ctl, [0.0, 0.0], 3, proposal=5.0)
    assert trace.fallbacks == ["projected_proposal"] * 3
    assert np.all(trace.inputs == 3.0)  # u_p = 5 projected onto |u| <= 3


def test_non_finite_state_is_a_recorded_fallback(pend, controller):
    u, info = controller.step(np.array([np.nan, 0.0]), np.array([1.0]))
    assert info.fallback == "projected_proposal" and info.status == "non_finite_state"
    assert u[0] == 1.0


def test_non_finite_proposal_is_filtered_as_zero(pend, controller, unstable2d_tube):
    """NaN/inf entries of u_p are runtime data: read as 0 and filtered (the applied input
    is the filter's, certified), recorded as non_finite_proposal, never raised; a wrong
    shape still raises (PCBF (2.23) and robust Algorithm 5.2)."""
    from balustrade.control.robust import RobustPCBFSafetyFilter
    from balustrade.errors import BalustradeError, ShapeError

    d = unstable2d_tube
    s, cbf = d["s"], d["cbf"]
    robust = RobustPCBFSafetyFilter.build(d["system"], s.X, s.U, cbf, cbf.policy, d["N"],
                                          s.deltas(), d["error"], s.alpha_f, target="cvxpy")
    for ctl, x in ((controller, np.array([0.45, 1.0])), (robust, np.array([0.3, 0.2]))):
        ctl.reset()
        u0, info0 = ctl.step(x, np.array([0.0]))
        assert info0.status == "ok"
        for bad in (np.nan, np.inf, -np.inf):
            ctl.reset()
            u, info = ctl.step(x, np.array([bad]))
            assert u == pytest.approx(u0, abs=1e-7)
            assert info.status == "non_finite_proposal" and info.fallback is None
            assert info.values["non_finite_proposal"] == 1.0
        with pytest.raises(ShapeError, match="step: u_p"):
            ctl.step(x, np.zeros(2))
        with pytest.raises(BalustradeError, match="step: u_p"):
            ctl.step(x, "junk")
    assert controller.step(np.array([0.45, 1.0]), np.array([0.0]))[0][0] < -2.9  # it acts


def test_controller_arguments_are_validated():
    from balustrade.control.fallbacks import project
    from balustrade.control.multiobjective import MultiobjectiveLyapunovController
    from balustrade.dsl import Box
    from balustrade.errors import BalustradeError, ShapeError

    with pytest.raises(BalustradeError, match="rho"):
        MultiobjectiveLyapunovController(None, None, None, rho="a")
    with pytest.raises(BalustradeError, match=r"rho.*\[0, 1\)"):
        MultiobjectiveLyapunovController(None, None, None, rho=1.0)
    with pytest.raises(BalustradeError, match="project: u"):
        project("junk", Box.symmetric([1.0]))
    with pytest.raises(ShapeError, match="project: u"):
        project(np.zeros(3), Box.symmetric([1.0]))
    assert project(np.array([np.nan]), Box.symmetric([1.0]))[0] == 0.0


def test_shifted_warm_start_is_the_shifted_plan(pend):
    """``warm_start="shifted"`` starts (2.24) from the last plan shifted by one step with the
    measured state first; the default starts from the last (2.24) solution; the emitted C only
    does the default, so a shifted filter is refused for C; a bad value names the option."""
    args = (pend.compiled["slack", "casadi"], pend.compiled["filter", "casadi"], pend.U)
    ctl = PCBFSafetyFilter(*args, warm_start="shifted")
    x = np.array([0.3, 0.5])
    assert ctl._slack_start(x) is None                      # nothing to shift yet
    u, info = ctl.step(x, np.array([3.0]))
    last = ctl._last_filter
    assert last is not None and last.success
    start = ctl._slack_start(np.array([0.31, 0.4]))
    X, U = np.asarray(last["x"]), np.asarray(last["u"])
    np.testing.assert_array_equal(start["x"][:, 0], [0.31, 0.4])
    np.testing.assert_array_equal(start["x"][:, 1:-1], X[:, 2:])
    np.testing.assert_array_equal(start["u"][:, :-1], U[:, 1:])
    assert not start["u"][:, -1].any()
    assert PCBFSafetyFilter(*args)._slack_start(x) is None   # "last": the (2.24) solution
    with pytest.raises(BalustradeError, match="warm_start"):
        ctl.deployment_spec()
    with pytest.raises(BalustradeError, match="warm_start"):
        PCBFSafetyFilter(*args, warm_start="previous")
