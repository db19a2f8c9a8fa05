"""``compare_backends`` keeps one entry per target, even when two targets share a name."""

from __future__ import annotations

import numpy as np

from balustrade.backends import Target
from balustrade.dsl.sets import Box
from balustrade.dsl.system import LinearSystem
from balustrade.problems.mpc import mpc_problem
from balustrade.testing import compare_backends


def test_two_unnamed_targets_are_both_solved():
    system = LinearSystem(np.array([[1.0, 0.1], [0.0, 1.0]]), np.array([[0.0], [0.1]]))
    ocp = mpc_problem(system, Box.symmetric([5.0, 5.0]), Box.symmetric([1.0]), None, 3,
                      np.eye(2), np.eye(1), np.eye(2))
    result = compare_backends(ocp, {"x0": [0.3, 0.1]},
                              targets=(Target("casadi", "ipopt"), Target("casadi", "sqpmethod")))
    assert list(result.objectives) == ["custom", "custom#2"]
    assert result.agree(), result.objectives
