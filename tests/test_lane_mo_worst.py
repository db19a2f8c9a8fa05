"""Algorithm 6.4's worst steps (issue #14, lane change, session 13): a (6.15) answered by the
interior-point retry of an ordinary step is followed by a (6.15) started from the candidate
(6.14), as after a recovery solve. From the interior-point primal–dual point the first SQP
attempt stopped after one QP of 0.7–1.4 s under load (lane change, seed 9, steps 99–101;
seed 2, step 106; docs/vehicles.md, "Session 13: Algorithm 6.4's worst steps").

On the unstable 2-D example of Section 5.6 with the SQP capped at 3 iterations (as
tests/test_lane_recovery.py), so that the interior-point retry answers ordinary steps. The
emitted C decides the same (``bal/problem.c``'s ``which``): equal attempts, statuses and
inputs bitwise.
"""

from __future__ import annotations

import ctypes

import numpy as np
import pytest
from test_emit_robust import _design
from test_lane_recovery import _counted, _lead_solver

from balustrade.backends import Solution
from balustrade.backends.targets import target
from balustrade.codegen import accelerate
from balustrade.control.multiobjective import MultiobjectivePCBFController
from balustrade.models.unstable2d import unstable2d, unstable2d_setup

STEPS = 8
#: a state from which the interior-point retry answers every (6.15) of the capped chain
START = np.array([0.1, 1.0])


def _capped() -> MultiobjectivePCBFController:
    base, _ = _design()
    s = unstable2d_setup(10)
    capped = target("robust-sqp", options={"max_iter": 3})
    return MultiobjectivePCBFController.build(
        unstable2d(), s.X, s.U, base.h_f, base.pi_f, 10, s.deltas(), base.error, s.alpha_f,
        target=capped, slack_target=capped)


def _next(ctrl: MultiobjectivePCBFController, x: np.ndarray, u: np.ndarray) -> np.ndarray:
    nw = ctrl.system.nw
    return np.asarray(ctrl.system.step(x, u, np.zeros(nw) if nw else None),
                      dtype=float).reshape(-1)


def test_after_an_interior_point_answer_the_next_problem_starts_from_the_candidate() -> None:
    """Fails on the previous code: there the (6.15) after a step answered by the
    interior-point retry started from that answer (a Solution), not from the candidate."""
    ctrl = _capped()
    led, name = _lead_solver(ctrl.problem)
    starts: list = []
    solve = ctrl.problem.solve

    def spy(params, warm_start=None, **kw):
        starts.append(warm_start)
        return solve(params, warm_start=warm_start, **kw)

    ctrl.problem.solve = spy
    x, answered, checked = START, [], 0
    for k in range(STEPS):
        cand = ctrl.candidate   # the candidate (6.14) this step starts from
        u, info = ctrl.step(x, np.array([1.0]))
        sol = info.solutions["problem"]
        answered.append(sol.success and sol.solver == name)
        if k >= 2 and answered[k - 1]:   # the previous (6.15): an interior-point retry
            assert not isinstance(starts[k], Solution), (k, type(starts[k]))
            assert np.array_equal(starts[k]["v"], cand.v), k
            checked += 1
        x = _next(ctrl, x, u)
    assert checked >= 2, answered   # ordinary steps the interior-point retry answered


def _sol(status: str, function: str) -> Solution:
    return Solution(status=status, objective=0.0, primal={}, dual={}, solve_time=0.0,
                    iterations=1, backend="casadi", solver="test", raw={"function": function})


def test_which_answers_count_as_the_recovery_attempts() -> None:
    """Only a converged answer of the recovery attempt's solver counts (not the SQP's, not a
    failed one, and none without a recovery target)."""
    ctrl = _capped()
    led, _ = _lead_solver(ctrl.problem)
    assert not ctrl._answered_by_lead(_sol("optimal", ctrl.problem.solver.name()))
    assert ctrl._answered_by_lead(_sol("optimal", led.name()))
    assert not ctrl._answered_by_lead(_sol("failed", led.name()))
    ctrl.recovery_target = None   # no recovery attempt: no such rule
    assert not ctrl._answered_by_lead(_sol("optimal", led.name()))


@pytest.fixture(scope="module")
def mo_c(tmp_path_factory: pytest.TempPathFactory) -> tuple:
    py = _capped()
    return py, accelerate(py, build_dir=tmp_path_factory.mktemp("mo_worst"), name="moworst")


def test_c_starts_from_the_candidate_as_python(mo_c: tuple) -> None:
    """The C runs the same attempts with the same inputs, bitwise, along a loop in which the
    interior-point retry answers ordinary steps (on a C without the rule its SQP starts from
    the interior-point point and the loops differ)."""
    py, c = mo_c
    attempts = c._lib.fn(f"{c.problem.info['prefix']}_attempts", ctypes.c_int,
                         [ctypes.c_void_p])
    runs = _counted(py.problem)
    led, _ = _lead_solver(py.problem)
    py.reset()
    c.reset()
    x, after_ip = START, 0
    for k in range(STEPS):
        runs.clear()
        (u1, i1), (u2, i2) = py.step(x, np.array([1.0])), c.step(x, np.array([1.0]))
        assert i1.fallback == i2.fallback, k
        assert np.array_equal(u1, u2), (k, u1, u2)
        assert attempts(c.problem.work) == len(runs), k
        after_ip += k >= 2 and py._recovered
        x = _next(py, x, u1)
    assert after_ip >= 2
