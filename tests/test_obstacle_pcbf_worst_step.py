"""The worst step of the §8.3 PCBF algorithm (issue #16, session 13; docs/obstacles.md
"session 13"): from (−0.5, −1.5), step 48, a certified step whose (2.23) fatrop cannot
solve from any start (it stalls at ``inf_du`` ≈ 8.8e-5 with its regularization at 1e4 until
``max_iter``). Session 12's chain ran fatrop from the last solution, from the shifted plan
and cold (3 × 301 iterations), then IPOPT cold (203): 0.6 s idle, 0.85–1.8 s under load.
With ``shifted_retry_solver = -1`` (:data:`~balustrade.reproduce.obstacles.
SHIFTED_RETRY_SOLVER`) the chain's IPOPT runs from the certified plan right after the first
fatrop attempt and converges in a few iterations to the optimum IPOPT reaches cold.
Session 14: fatrop's stall stop (:data:`~balustrade.reproduce.obstacles.STALL`) ends
that first attempt as a failure after ~32 instead of 301 iterations; the same IPOPT attempt
then gives the same answer."""

from __future__ import annotations

import numpy as np
import pytest

from balustrade.control.plant import check_plant
from balustrade.models.obstacle_car import obstacle_car
from balustrade.reproduce import obstacles as O

START, STEP = (-0.5, -1.5), 48


def _attempts_at_worst_step(shifted_retry_solver: int, stall_stop: object = O.STALL
                            ) -> tuple[list[tuple], object]:
    """Run the reference loop from ``START`` to ``STEP`` and record that step's (2.23)
    attempts as (solver, status, iterations, message)."""
    f = O.pcbf_algorithm("structured-ip", shifted=False,
                         shifted_retry_solver=shifted_retry_solver, stall_stop=stall_stop)
    plant = check_plant(obstacle_car(), "worst step")
    mpc, x = O.NaiveMPC(), O.initial_state(START)
    mpc.start(x)
    for k in range(STEP):
        u, _ = f.step(x, mpc(k, x))
        x = plant.step(x, u, None)
    calls: list[tuple] = []
    inner = f.filter._solve_with

    def recording(solver, p, guess):
        s = inner(solver, p, guess)
        calls.append((s.solver, str(s.status), s.iterations, s.message))
        return s

    f.filter._solve_with = recording
    _, info = f.step(x, mpc(STEP, x))
    return calls, info


@pytest.mark.slow
def test_ipopt_from_the_plan_follows_the_stalled_first_attempt():
    assert O.SHIFTED_RETRY_SOLVER == -1
    calls, info = _attempts_at_worst_step(O.SHIFTED_RETRY_SOLVER)
    assert info.status == "certified" and info.fallback is None
    assert [c[0] for c in calls] == ["fatrop", "ipopt"]
    assert calls[0][1] != "optimal" and calls[1][1] == "optimal"
    assert calls[1][2] < 50  # from the plan (cold: ~200 iterations)
    old, info_old = _attempts_at_worst_step(0)  # session 12: fatrop 3 times, IPOPT cold
    assert [c[0] for c in old] == ["fatrop", "fatrop", "fatrop", "ipopt"]
    assert old[-1][2] > calls[1][2]
    # the same optimum, reached cold or from the plan
    np.testing.assert_allclose(info.solutions["filter"].objective,
                               info_old.solutions["filter"].objective, rtol=1e-6)


@pytest.mark.slow
def test_the_stall_stop_ends_the_first_attempt_early_with_the_same_answer():
    """With the stall stop the first fatrop attempt fails as ``StopAtAcceptablePoint`` in
    fewer than 60 iterations (measured 32: ~12 to primal feasibility, then the 20 of
    ``acceptable_iter``); without it, it runs to ``max_iter`` (301). IPOPT from the plan
    follows either way, with the same input and objective."""
    calls, info = _attempts_at_worst_step(O.SHIFTED_RETRY_SOLVER)
    off, info_off = _attempts_at_worst_step(O.SHIFTED_RETRY_SOLVER, stall_stop=None)
    assert [c[0] for c in calls] == [c[0] for c in off] == ["fatrop", "ipopt"]
    assert calls[0][3].startswith("fatrop: StopAtAcceptablePoint") and calls[0][2] < 60
    assert calls[0][1] == "failed"
    assert off[0][3].startswith("fatrop: MaxIterExceeded") and off[0][2] > 300
    assert info.status == info_off.status == "certified"
    np.testing.assert_array_equal(info.solutions["filter"].w,
                                  info_off.solutions["filter"].w)
