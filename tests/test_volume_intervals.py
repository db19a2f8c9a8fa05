"""Honest intervals of the admissible-set volumes (session 13, audit finding 4): undecided
samples widen the volume interval to ``[Wilson(k).lo, Wilson(k + u).hi]``, and the paired
growth interval comes from the samples in one set but not the other, so it is never
``[0, 0]`` when no sample differs."""

from __future__ import annotations

import numpy as np
import pytest

from balustrade.design.admissible_volume import (
    FEASIBLE,
    INFEASIBLE,
    UNDECIDED,
    admissible_volumes,
    paired_growth_interval,
    volume_interval,
    wilson_interval,
)
from balustrade.dsl.sets import Box


class _Fixed:
    """A decider with fixed outcome fractions (feasible first, then undecided)."""

    def __init__(self, feasible: float, undecided: float):
        self.f, self.u = feasible, undecided

    def feasible(self, xs: np.ndarray, progress: object = None) -> np.ndarray:
        n = len(xs)
        out = np.full(n, INFEASIBLE, dtype=np.int8)
        out[: int(self.f * n)] = FEASIBLE
        out[int(self.f * n): int((self.f + self.u) * n)] = UNDECIDED
        return out


def test_undecided_samples_widen_the_volume_interval():
    X = Box([0.0], [1.0])
    rep = admissible_volumes({"A": _Fixed(0.5, 0.0), "B": _Fixed(0.5, 0.1)}, X, 2000,
                             order=("A", "B"))
    a, b = rep.estimates["A"], rep.estimates["B"]
    assert a.volume == b.volume == 0.5 and b.undecided == 200
    assert a.interval == pytest.approx(wilson_interval(1000, 2000))
    # every undecided sample of B feasible: fraction 0.60, inside B's interval
    assert b.interval[0] == pytest.approx(a.interval[0])
    assert b.interval[1] >= wilson_interval(1200, 2000)[1] > 0.6
    assert volume_interval(1000, 200, 2000) == pytest.approx(b.interval)
    g = rep.growth("A", "B")
    assert g["growth"] == 0.0 and g["ci95"][0] < 0.0 and g["ci95"][1] > 0.2  # B up to +20 %


def test_growth_interval_of_identical_sets_is_not_a_point():
    same = np.array([FEASIBLE] * 170 + [INFEASIBLE] * 30)
    lo, hi, counts = paired_growth_interval(same, same)
    assert counts == {"only_large": 0, "only_small": 0, "union": 170}
    assert -0.05 < lo < -0.01 and 0.01 < hi < 0.05           # about ±3 % from 170 samples
    # 200 of 200 in both: about ±2.5 %
    lo, hi, _ = paired_growth_interval(np.ones(200, np.int8), np.ones(200, np.int8))
    assert hi == pytest.approx(1 / (1 - wilson_interval(0, 200, 2.241402727604947)[1]) - 1)
    assert 0.02 < hi < 0.03 and lo == pytest.approx(-hi / (1 + hi))


def test_growth_interval_covers_a_known_ratio():
    """Paired samples of the nested intervals [0, 0.25] ⊆ [0, 0.5] of [0, 1]: ratio 2,
    growth +100 %; the interval covers it for most seeds (95 % nominal)."""
    hits = 0
    for seed in range(40):
        x = np.random.default_rng(seed).uniform(0, 1, 400)
        small = np.where(x <= 0.25, FEASIBLE, INFEASIBLE).astype(np.int8)
        large = np.where(x <= 0.5, FEASIBLE, INFEASIBLE).astype(np.int8)
        lo, hi, _ = paired_growth_interval(small, large)
        hits += lo <= 1.0 <= hi
    assert hits >= 36
