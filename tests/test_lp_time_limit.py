"""A feasibility LP stopped by its time limit is undecided, never feasible or infeasible; the
limit is per sample and does not outlive the call (session 9: an 8-mass re-check LP ran for
over 30 min with no limit and no progress; HiGHS compares ``time_limit`` with its solver
object's cumulative run time, which the thread-local solver keeps across calls)."""

import highspy
import numpy as np
import scipy.sparse as sp

from balustrade.backends.lp import _highs
from balustrade.backends.lp_batch import FEASIBLE, UNDECIDED, BatchLP, feasible_many


def _batch(m: int, n: int, copies: int) -> tuple[BatchLP, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    A = sp.random(m, n, density=0.01, random_state=1, format="csr")
    b = A @ rng.uniform(-1.0, 1.0, n)
    lp = BatchLP.build(A, -10.0 * np.ones(n), 10.0 * np.ones(n))
    return lp, np.vstack([b - 1e-3] * copies), np.vstack([b + 1e-3] * copies)


def test_a_time_limited_lp_is_undecided() -> None:
    lp, lo, hi = _batch(3000, 2000, 2)
    seen: list[int] = []
    out = feasible_many(lp, lo, hi, seen.append, time_limit=1e-4)
    assert np.all(out == UNDECIDED) and seen == [0, 1]


def test_the_limit_is_per_sample_not_on_the_solvers_cumulative_clock() -> None:
    lp, lo, hi = _batch(200, 150, 1)
    solver = _highs(highspy)
    while solver.getRunTime() < 0.5:             # the thread-local solver's clock runs on
        assert np.all(feasible_many(lp, lo, hi) == FEASIBLE)
    assert np.all(feasible_many(lp, lo, hi, time_limit=0.25) == FEASIBLE)
    assert np.all(feasible_many(lp, lo, hi) == FEASIBLE)       # no limit left behind
