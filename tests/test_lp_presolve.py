"""HiGHS' presolve has called thin, non-empty parameter sets empty (session 10: the 8-mass box
update of ``reproduce.msd_seeded`` seed 3 reported the true model falsified, θ* meeting every
row to 4e-16). An ``infeasible`` verdict of :mod:`balustrade.backends.lp` now needs a
presolve-free solve and a valid Farkas ray; these tests fail on the presolve-only verdict
(3 of the 300 seeded sets below are called empty by ``linprog``/HiGHS with presolve)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.optimize

from balustrade.backends.lp import is_feasible, solve_lp, solve_lps, solve_lps_joint
from balustrade.backends.lp_batch import FEASIBLE, INFEASIBLE, BatchLP, feasible_many
from balustrade.backends.solution import Status
from balustrade.errors import EmptySetError


def _thin_sets(count: int, seed: int = 0, shift: float = 0.0):
    """Box ``[0.05, 0.25]^7`` flat to 2e-9 around θ* in one coordinate, intersected with
    slabs ``|aᵀθ − b| <= 1e-3`` whose boundary passes through θ* (vertex disturbances), as
    in a box update of the §4.7 chain; ``shift > 0`` adds the row ``θ_j >= θ*_j + shift``
    for the flat coordinate ``j`` (then the set is empty, by ``shift − 1e-9``)."""
    rng = np.random.default_rng(seed)
    for _ in range(count):
        q = 7
        theta = rng.uniform(0.05, 0.25, q)
        lb, ub = np.full(q, 0.05), np.full(q, 0.25)
        j = rng.integers(q)
        lb[j], ub[j] = theta[j] - 1e-9, theta[j] + 1e-9
        A = rng.normal(size=(8, q)) * rng.choice([1.0, 1e-3, 0.0], (8, q))
        side = rng.choice([-1.0, 1.0], 8)
        b = A @ theta + 1e-3 * side
        H = np.vstack([np.eye(q), -np.eye(q), A, -A])
        h = np.concatenate([ub, -lb, b + 1e-3, 1e-3 - b])
        if shift > 0.0:
            H = np.vstack([H, -np.eye(q)[j]])
            h = np.append(h, -(theta[j] + shift))
        yield theta, H, h


def test_presolve_alone_calls_some_of_these_sets_empty():
    """The premise: without the re-check HiGHS (through linprog) gets some of them wrong."""
    wrong = sum(scipy.optimize.linprog(np.zeros(7), A_ub=H, b_ub=h, bounds=[(None, None)] * 7,
                                       method="highs").status == 2
                for _, H, h in _thin_sets(300))
    assert wrong >= 1


def test_thin_nonempty_sets_are_feasible_and_bounds_contain_theta_star():
    for theta, H, h in _thin_sets(300):
        assert np.max(H @ theta - h) <= 1e-12
        assert is_feasible(H, h) is Status.OPTIMAL
        C = np.vstack([np.eye(7), -np.eye(7)])
        for results in (solve_lps_joint(C, H, h), solve_lps(C, H, h)):
            assert all(r.status is Status.OPTIMAL for r in results) and len(results) == 14
            values = np.array([r.value for r in results])
            assert np.all(values[:7] >= theta - 1e-7) and np.all(-values[7:] <= theta + 1e-7)
        assert solve_lp(np.ones(7), H, h).status is Status.OPTIMAL


def test_really_empty_sets_stay_infeasible():
    """The flat coordinate pushed 1e-6 past its box: the sets are empty, and the checked
    verdict says so (a valid Farkas ray) on every path."""
    for _, H, h in _thin_sets(60, seed=1, shift=1e-6):
        assert scipy.optimize.linprog(np.zeros(7), A_ub=H, b_ub=h,
                                      bounds=[(None, None)] * 7,
                                      method="highs", options={"presolve": False}).status == 2
        assert is_feasible(H, h) is Status.INFEASIBLE
        assert solve_lps_joint(np.eye(7), H, h)[-1].status is Status.INFEASIBLE
        assert solve_lp(np.ones(7), H, h).status is Status.INFEASIBLE


def test_batch_feasibility_rechecks_infeasible_samples():
    """``feasible_many`` on the same sets as one batch (rows ``Hθ <= h``, θ free)."""
    sets = list(_thin_sets(300)) + list(_thin_sets(20, seed=1, shift=1e-6))
    # each set has its own rows: one batch of one sample per set
    out = [feasible_many(BatchLP.build(H, np.full(7, -np.inf), np.full(7, np.inf)),
                         np.full((1, H.shape[0]), -np.inf), h[None, :])[0]
           for _, H, h in sets]
    assert all(o == FEASIBLE for o in out[:300])
    assert all(o == INFEASIBLE for o in out[300:])


def test_polytope_layer_does_not_call_thin_sets_empty():
    """The set layer (:class:`~balustrade.dsl.sets.Polytope`) uses the same re-decided
    verdict: ``is_empty`` and ``support`` on the thin sets above."""
    from balustrade.dsl.sets import Polytope

    for theta, H, h in _thin_sets(300):
        P = Polytope(H, h)
        assert not P.is_empty()
        assert P.support(np.ones(7)) >= float(np.sum(theta)) - 1e-7
    for _, H, h in _thin_sets(20, seed=1, shift=1e-6):
        with pytest.raises(EmptySetError):       # the constructor refuses an empty set
            Polytope(H, h)


def test_without_highspy_the_verdicts_do_not_recurse(monkeypatch):
    """``solve_lp`` re-decides an infeasible verdict without going back through itself (the
    review found ``solve_lp → is_feasible → solve_lps → solve_lp`` without highspy)."""
    import sys

    monkeypatch.setitem(sys.modules, "highspy", None)
    H, h = np.array([[1.0], [-1.0]]), np.array([0.0, -1e-3])
    assert solve_lp(np.ones(1), H, h).status is Status.INFEASIBLE
    assert is_feasible(H, h) is Status.INFEASIBLE
    assert solve_lps_joint(np.eye(1), H, h)[-1].status is Status.INFEASIBLE
    theta, H, h = next(_thin_sets(1))
    assert solve_lp(np.ones(7), H, h).status is Status.OPTIMAL
