"""Which ``StepInfo.status`` words count as a successful step
(:data:`balustrade.control.base.SUCCEEDED`, :func:`~balustrade.control.base.step_succeeded`),
per controller."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from balustrade.control.approximate import ApproximatePCBFFilter
from balustrade.control.base import SUCCEEDED, TRUNCATED, step_succeeded
from balustrade.models.pendulum import pendulum, pendulum_setup

#: controller -> (status words of a successful step, of a failed / fallback / bad-data step)
WORDS = {
    "PCBFSafetyFilter (Alg. 2)": (
        ["ok", "certified"],
        ["slack_feasible_filter_optimal", "filter_infeasible", "certified_filter_infeasible",
         "slack_truncated_filter_optimal", "non_finite_proposal", "non_finite_state"]),
    "ApproximatePCBFFilter (Alg. 7.5)": (
        ["ok", "certified", "proposal_feasible"],
        ["filter_feasible", "filter_infeasible", "max_decrease_failed", "error: boom",
         "non_finite_state", "non_finite_proposal", "non_finite_proposal_filter_feasible"]),
    "GridPCBFFilter (Alg. 8.7)": (
        ["ok"],
        ["no_decreasing_candidate", "non_finite_state", "non_finite_proposal"]),
    # control/robust.py and codegen/runtime_robust.robust_info: a solve that did not end
    # optimal names itself (an applied optimal_inaccurate or feasible truncated one too)
    "RobustPCBFSafetyFilter (Alg. 5.2)": (
        ["ok"],
        ["slack_above_candidate", "slack_infeasible", "slack_max_iterations", "slack_failed",
         "slack_feasible", "slack_truncated", "slack_not_converged", "slack_eval_error",
         "slack_optimal_inaccurate", "filter_optimal_inaccurate",
         "slack_optimal_inaccurate_filter_truncated", "filter_truncated", "filter_infeasible",
         "filter_not_converged", "non_finite_state", "non_finite_proposal",
         "non_finite_proposal_slack_above_candidate"]),
    # control/multiobjective.py and codegen/runtime_robust.multiobjective_info. An applied
    # optimal_inaccurate (6.15) is "ok" with uncertified["problem"] (the C cannot see
    # IPOPT's acceptable stop: docs/vehicles.md, "session 12")
    "MultiobjectivePCBFController (Alg. 6.4)": (
        ["ok"],
        ["problem_above_bound", "problem_infeasible", "problem_max_iterations",
         "problem_failed", "problem_feasible", "problem_truncated", "problem_not_converged",
         "problem_eval_error", "init_infeasible", "init_failed", "init_not_converged",
         "non_finite_state", "non_finite_proposal", "non_finite_proposal_problem_above_bound"]),
}


@pytest.mark.parametrize("controller", sorted(WORDS))
def test_success_and_failure_words(controller):
    good, bad = WORDS[controller]
    assert all(step_succeeded(w) for w in good), [w for w in good if not step_succeeded(w)]
    assert not any(step_succeeded(w) for w in bad), [w for w in bad if step_succeeded(w)]
    assert not step_succeeded(TRUNCATED)


def test_succeeded_is_exactly_the_listed_words():
    assert SUCCEEDED == frozenset(w for good, _ in WORDS.values() for w in good)


def test_proposal_feasible_step_of_algorithm_7_5_succeeds():
    """A real Algorithm 7.5 step where ``u_p`` is the exact minimiser of (7.5) (no
    certification, ``exact_shortcut``): status ``proposal_feasible``, no fallback, a success."""
    P = np.array([[4.246, 0.212], [0.212, 0.460]])
    f = ApproximatePCBFFilter(pendulum(), pendulum_setup().U,
                              lambda x: ca.mtimes([x.T, P, x]) - 1, certify=False, rho=0.1)
    u, info = f.step(np.array([0.1, -0.5]), np.array([0.0]))
    assert info.status == "proposal_feasible" and info.fallback is None
    assert step_succeeded(info.status) and u[0] == 0.0
