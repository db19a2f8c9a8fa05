"""Horizon sweep of the rendezvous filters (thesis Section 6.5): the Algorithm 5.2 step
((5.15) then (5.16)) and the Algorithm 6.4 step (one (6.15) solve) for
``N ∈ {25, 50, 100, 200, 400}`` (``quick``: ``{25, 50, 100}``), every path of
:mod:`benchmarks.bench_robust` (balustrade default, exact, long-horizon, cvxpy, fast-convex
when present, and the hand-written Clarabel baseline), timed interleaved on the same states.

Per path and algorithm the fitted exponent ``a`` of ``t ∝ N^a`` (least squares of
``log t`` on ``log N`` over the medians) is reported: ``a ≈ 1`` is a solver that exploits the
stage structure (sparse KKT), ``a`` near 2–3 one that does not. The baseline is verified
against the cvxpy path at every ``N`` (:func:`benchmarks.bench_robust.verify`).
"""

from __future__ import annotations

import numpy as np

from balustrade.reproduce.rendezvous import design
from benchmarks._clarabel_direct import DirectRendezvous, RendezvousData
from benchmarks.bench_robust import (
    BASELINE,
    build_paths,
    closed_loop_states,
    measure,
    verify,
)

HORIZONS, QUICK_HORIZONS = (25, 50, 100, 200, 400), (25, 50, 100)


def fitted_exponent(N: np.ndarray, t: np.ndarray) -> float:
    """``a`` of ``t ≈ c N^a``: the least-squares slope of ``log t`` against ``log N``."""
    N, t = np.asarray(N, dtype=float), np.asarray(t, dtype=float)
    keep = np.isfinite(t) & (t > 0)
    if keep.sum() < 2:
        return float("nan")
    slope, _ = np.polyfit(np.log(N[keep]), np.log(t[keep]), 1)
    return float(slope)


def sweep(horizons: tuple[int, ...], n_states: int) -> tuple[dict, dict, list[dict]]:
    """``({(alg, label): [median per N]}, {label: reason not available}, rows per N)``."""
    medians: dict = {}
    missing: dict = {}
    rows = []
    for N in horizons:
        d = design(N, 40)
        direct = DirectRendezvous(RendezvousData.from_design(d))
        states = closed_loop_states(d, direct, n_states + 1)
        paths, missing = build_paths(d)
        times, checks = measure(d, states, paths, direct)
        verify(checks)
        for (alg, label), pt in times.items():
            st = pt.stats()
            medians.setdefault((alg, label), []).append(st["median_s"])
            rows.append({"name": f"horizon Alg {alg} N={N}: {label}", **st})
    return medians, missing, rows


def run(quick: bool = False) -> list[dict]:
    horizons = QUICK_HORIZONS if quick else HORIZONS
    medians, missing, rows = sweep(horizons, 3 if quick else 5)
    N = np.array(horizons, dtype=float)
    for (alg, label), t in medians.items():
        base = medians[(alg, BASELINE)]
        rows.append({"name": f"horizon Alg {alg}: {label} t ∝ N^a",
                     "exponent": round(fitted_exponent(N, np.array(t)), 2),
                     "N": list(horizons), "median_ms": [round(1e3 * v, 2) for v in t],
                     "x_handwritten": [round(a / b, 1) for a, b in zip(t, base, strict=True)]})
    for label, reason in missing.items():
        rows.append({"name": f"horizon: {label}", "status": reason})
    return rows
