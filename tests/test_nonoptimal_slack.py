"""A slack problem not solved to optimality is never used as h_PB / h_r without saying so
(issue #12): forced non-converged (2.24) solves (IPOPT stopped after 5 iterations, which
ends primal feasible far from the optimum) and a flagged ``optimal_inaccurate`` (5.15)."""

from __future__ import annotations

import numpy as np
import pytest

from balustrade.backends import compile
from balustrade.control import PCBFSafetyFilter, simulate
from balustrade.control.robust import RobustPCBFSafetyFilter

X_OUT = np.array([0.49, 0.5])   # outside S_PB: h_PB = 0.041 (cvxpy)


@pytest.fixture(scope="module")
def truncated(pend):
    """(2.24) (1-norm, as ``pend.slack``) with IPOPT stopped after 5 iterations, no retries:
    the result is primal feasible but not converged (status ``feasible``)."""
    return compile(pend.slack, "casadi", "ipopt", {"ipopt.max_iter": 5}, retries=[])


def test_truncated_solve_is_feasible_not_optimal(pend, truncated):
    sol = truncated.solve({"x0": X_OUT})
    exact = pend.compiled["slack", "cvxpy"].solve({"x0": X_OUT})
    assert sol.status == "feasible" and "Maximum_Iterations" in sol.message
    assert sol.objective > exact.objective + 1.0   # far off: must not be reported as h_PB


def test_pcbf_filter_does_not_use_a_feasible_slack_value_as_h_pb(pend, truncated):
    ctl = PCBFSafetyFilter(pend.compiled["slack", "casadi"], pend.compiled["filter", "casadi"],
                           pend.U)
    u0, info0 = ctl.step(X_OUT, np.array([2.0]))                # a plan from an optimal step
    assert info0.status == "ok" and not info0.uncertified
    plan = ctl._plan.copy()
    ctl.slack = truncated
    x1 = pend.system.step(X_OUT, u0)
    u1, info = ctl.step(x1, np.array([2.0]))
    assert info.uncertified == {"slack": "feasible"}
    assert info.status == "slack_feasible"
    assert np.isnan(info.values["h_PB"])
    exact = pend.compiled["slack", "cvxpy"].solve({"x0": x1}).objective
    assert info.values["h_PB_upper"] >= exact - 1e-9           # an upper bound, labelled so
    # the thesis' candidate after a failed (2.24): the shifted plan of the last optimal step
    assert info.fallback == "shifted_plan" and u1 == pytest.approx(plan[:, 1])


def test_without_a_plan_the_feasible_slack_is_used_and_flagged(pend, truncated):
    ctl = PCBFSafetyFilter(truncated, pend.compiled["filter", "casadi"], pend.U)
    u, info = ctl.step(X_OUT, np.array([2.0]))
    assert info.fallback == "feasible_slack" and info.uncertified["slack"] == "feasible"
    assert np.isnan(info.values["h_PB"]) and info.status.startswith("slack_feasible")
    assert pend.U.contains(u)


def test_trace_counts_uncertified_steps(pend, truncated):
    ctl = PCBFSafetyFilter(truncated, pend.compiled["filter", "casadi"], pend.U)
    trace = simulate(pend.system, ctl, X_OUT, 3, proposal=2.0)
    assert trace.n_uncertified == 3 and all(u == {"slack": "feasible"} or "slack" in u
                                            for u in trace.uncertified)
    assert np.all(np.isnan(trace.values["h_PB"]))
    good = PCBFSafetyFilter(pend.compiled["slack", "casadi"], pend.compiled["filter", "casadi"],
                            pend.U)
    assert simulate(pend.system, good, X_OUT, 3, proposal=2.0).n_uncertified == 0


class _Inaccurate:
    """A compiled problem whose solutions are relabelled ``optimal_inaccurate``."""

    def __init__(self, compiled):
        self.compiled, self.ocp = compiled, compiled.ocp

    def solve(self, params=None, warm_start=None):
        sol = self.compiled.solve(params, warm_start)
        sol.status = "optimal_inaccurate"
        return sol


def test_robust_filter_flags_an_inaccurate_h_r(unstable2d_tube):
    d = unstable2d_tube
    s, cbf = d["s"], d["cbf"]
    ctl = RobustPCBFSafetyFilter.build(d["system"], s.X, s.U, cbf, cbf.policy, d["N"],
                                       s.deltas(), d["error"], s.alpha_f, target="cvxpy")
    x = np.array([0.3, 0.2])
    _, info = ctl.step(x, np.array([0.5]))
    assert info.status == "ok" and not info.uncertified
    ctl.reset()
    ctl.slack = _Inaccurate(ctl.slack)
    _, info = ctl.step(x, np.array([0.5]))
    assert info.uncertified == {"slack": "optimal_inaccurate"}
    assert info.status == "slack_optimal_inaccurate" and np.isfinite(info.values["h_r"])


def test_a_feasible_point_of_cost_zero_is_certified_by_the_lower_bound(pend):
    """h_PB >= 0: sqpmethod's unconverged zero step at the origin (cost 0) is optimal all
    the same, and used as such (as the emitted C does)."""
    slack = compile(pend.slack, "casadi", "sqpmethod", retries=[])
    sol = slack.solve({"x0": [0.0, 0.0]})
    assert sol.status == "feasible" and sol.objective == pytest.approx(0.0, abs=1e-12)
    ctl = PCBFSafetyFilter(slack, pend.compiled["filter", "casadi"], pend.U)
    _, info = ctl.step(np.zeros(2), np.array([2.0]))
    assert info.status == "ok" and info.fallback is None and not info.uncertified
    assert info.values["h_PB"] == pytest.approx(0.0, abs=1e-12)
