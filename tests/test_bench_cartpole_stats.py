"""benchmarks/bench_cartpole.py: (2.24)'s iteration statistics count solved steps only."""

from __future__ import annotations

import numpy as np

from benchmarks.bench_cartpole import slack_iteration_stats


def test_skipped_steps_are_not_zero_iterations():
    """Steps whose (2.24) ``certificate_first`` skipped (0 iterations recorded) are counted
    apart, not as 0 in the median (which made the default pair's median 0)."""
    its = np.array([[0, 9], [0, 8], [0, 7], [12, 10], [14, 11]])
    st = slack_iteration_stats(its, [True, True, True, False, False])
    assert st == {"skipped_slack_solves": 3, "slack_solved_steps": 2,
                  "slack_iters_median": 13.0, "slack_iters_max": 14}
    none = slack_iteration_stats(its[:2], [True, True])
    assert none["slack_iters_median"] is None and none["slack_solved_steps"] == 0
