"""``bench_robust.measure`` with repeated passes: the fast paths are timed on every pass, the
slow ones once, the first state of every pass is a warm-up left out of the statistics."""

from __future__ import annotations

from balustrade.reproduce.rendezvous import design
from benchmarks._clarabel_direct import DirectRendezvous, RendezvousData
from benchmarks.bench_robust import BASELINE, PathTimes, build_paths, closed_loop_states, measure


def test_repeated_passes_time_fast_paths_again_and_drop_each_warmup():
    d = design(10, 10)
    direct = DirectRendezvous(RendezvousData.from_design(d))
    states = closed_loop_states(d, direct, 3)
    paths, _ = build_paths(d, ("cvxpy", "fast-convex"))
    times, checks = measure(d, states, paths, direct, repeats=2, slow=("cvxpy",))
    for alg in ("5.2", "6.4"):
        assert len(times[(alg, "fast-convex")].times) == 6
        assert len(times[(alg, BASELINE)].times) == 6
        assert len(times[(alg, "cvxpy")].times) == 3
        assert times[(alg, "fast-convex")].stats()["samples"] == 4     # 2 warm-ups dropped
        assert times[(alg, "cvxpy")].stats()["samples"] == 2
    assert checks[("5.2", "cvxpy")].compared >= 2


def test_path_times_without_marked_warmups_drop_the_first_samples():
    p = PathTimes()
    for t in (9.0, 1.0, 2.0, 3.0):
        p.add(t, True)
    assert p.stats()["median_s"] == 2.0 and p.stats()["samples"] == 3
    assert p.stats(skip=0)["median_s"] == 2.5
    q = PathTimes()
    for _ in range(2):
        for j, t in enumerate((9.0, 1.0, 2.0)):
            q.add(t, True, 0, j == 0)
    assert q.stats()["median_s"] == 1.5 and q.stats()["worst_ms"] == 2000.0
