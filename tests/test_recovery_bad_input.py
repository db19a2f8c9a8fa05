"""Bad ``recovery_target`` and ``lead`` values are refused where they are given, naming the
argument (review of session 13): a typo used to pass construction and raise inside a later
``step`` (Algorithm 5.2 at its second step), and ``solve(lead=5)`` raised an IndexError."""

from __future__ import annotations

import numpy as np
import pytest
from test_emit_robust import _design

from balustrade.backends import check_recovery_target
from balustrade.control.multiobjective import MultiobjectivePCBFController
from balustrade.control.robust import RobustPCBFSafetyFilter
from balustrade.errors import BalustradeError


@pytest.mark.parametrize("bad", ["recovey", 5, 1.5])
def test_a_bad_recovery_target_is_refused_at_construction(bad: object) -> None:
    with pytest.raises(BalustradeError, match="recovery_target"):
        check_recovery_target(bad, "Algorithm 5.2")
    c, _ = _design()
    with pytest.raises(BalustradeError, match="RobustPCBFSafetyFilter: recovery_target"):
        RobustPCBFSafetyFilter(c.slack, c.filter, c.system, c.X_E, c.U, c.error, c.h_f,
                               c.pi_f, c.deltas, c.alpha_f, c.slack_norm, c.U_E,
                               recovery_target=bad)
    with pytest.raises(BalustradeError, match="Algorithm 6.4: recovery_target"):
        MultiobjectivePCBFController(c.slack, c.filter, c.system, c.X_E, c.U, c.U_E,
                                     c.error, c.h_f, c.pi_f, c.deltas, c.alpha_f,
                                     recovery_target=bad)
    assert check_recovery_target(None, "x") is None
    assert check_recovery_target("recovery", "x") == "recovery"


@pytest.mark.parametrize("bad", [-1, 99, 1.5, True])
def test_a_bad_lead_is_refused_before_any_solve(bad: object) -> None:
    ctrl, _ = _design()
    with pytest.raises(BalustradeError, match="lead"):
        ctrl.slack.solve({"x0": np.array([0.9, 8.0])}, lead=bad)
