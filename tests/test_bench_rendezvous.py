"""The hand-written Clarabel baseline of the rendezvous benchmarks (benchmarks/_clarabel_direct)
agrees with balustrade on a small horizon, so its speed comparisons compare the same problems;
and the horizon sweep's exponent fit is right."""

from __future__ import annotations

import numpy as np
import pytest

from balustrade.reproduce.rendezvous import controllers, design
from benchmarks._clarabel_direct import DirectRendezvous, RendezvousData
from benchmarks.bench_horizon import fitted_exponent
from benchmarks.bench_robust import (
    BaselineMismatch,
    Check,
    PathTimes,
    build_paths,
    closed_loop_states,
    measure,
    paired_ratio,
    verify,
)

N = 12


@pytest.fixture(scope="module")
def setup():
    d = design(N, 10)
    return d, DirectRendezvous(RendezvousData.from_design(d))


def test_baseline_agrees_with_balustrade_cvxpy(setup):
    d, direct = setup
    states = closed_loop_states(d, direct, 5)
    paths, missing = build_paths(d, ("cvxpy", "fast-convex"))
    times, checks = measure(d, states, paths, direct)
    verify(checks)                                  # raises on disagreement
    assert checks[("5.2", "cvxpy")].compared >= 4
    assert checks[("6.4", "cvxpy")].compared >= 4
    assert times[("5.2", "hand-written Clarabel")].failed == 0
    for key in (("5.2", "hand-written Clarabel"), ("6.4", "cvxpy")):   # iterations recorded
        assert times[key].stats()["iterations"] > 0
    if "fast-convex" in missing:
        assert "not available" in missing["fast-convex"]


def test_baseline_h_r_and_input_match_cvxpy_controller(setup):
    d, direct = setup
    robust = controllers(d, (), target="cvxpy", record_h_r=False)["robust"]
    x = closed_loop_states(d, direct, 2)[1]           # outside S_r, (5.16) solved by cvxpy
    u, info = robust.step(x, np.zeros(3))
    ok, u_d, h_r, fuel = direct.alg52(x)
    assert ok and info.status == "ok"
    assert h_r > 1.0                                  # the start is outside S_r: h_r > 0
    assert h_r == pytest.approx(info.values["h_r"], rel=1e-4)
    assert fuel == pytest.approx(info.solutions["filter"].objective, rel=1e-3)
    np.testing.assert_allclose(u_d, u, atol=5e-3)


def test_wrong_baseline_is_caught(setup):
    d, direct = setup
    bad = Check()
    bad.h_r, bad.compared = 50.0, 3
    with pytest.raises(BaselineMismatch, match="5.2"):
        verify({("5.2", "cvxpy"): bad})
    # a baseline without the tightenings Δ_i solves a different (5.15): the run raises
    data = RendezvousData.from_design(d)
    data.deltas = np.zeros_like(data.deltas)
    wrong = DirectRendezvous(data)
    states = closed_loop_states(d, direct, 3)
    paths, _ = build_paths(d, ("cvxpy",))
    _, checks = measure(d, states, paths, wrong)
    with pytest.raises(BaselineMismatch):
        verify(checks)


def test_fitted_exponent():
    N = np.array([25, 50, 100, 200])
    assert fitted_exponent(N, 3e-4 * N ** 1.2) == pytest.approx(1.2)
    assert fitted_exponent(N, 1e-6 * N ** 3.0) == pytest.approx(3.0)
    assert np.isnan(fitted_exponent(N[:1], np.array([1.0])))


def test_paired_ratio_is_the_median_of_per_state_ratios():
    """States of very different cost (here 10 vs 100) cancel in the paired ratio; the
    warm-up sample is left out; misaligned samples raise."""
    base, path = PathTimes(), PathTimes()
    for j, (tb, tp) in enumerate([(1.0, 50.0), (10.0, 11.0), (100.0, 90.0), (10.0, 9.5)]):
        base.add(tb, True, warmup=j == 0)
        path.add(tp, True, warmup=j == 0)
    assert paired_ratio(path, base) == pytest.approx(0.95)
    short = PathTimes()
    short.add(1.0, True, warmup=False)
    with pytest.raises(BaselineMismatch, match="aligned"):
        paired_ratio(short, base)
    with pytest.raises(BaselineMismatch, match="only 1"):     # more samples than the baseline
        paired_ratio(base, short)
