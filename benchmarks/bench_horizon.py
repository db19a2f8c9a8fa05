"""Horizon sweep of the rendezvous filters (thesis Section 6.5): the Algorithm 5.2 step
((5.15) then (5.16)) and the Algorithm 6.4 step (one (6.15) solve) for
``N ∈ {25, 50, 100, 200, 400}`` (``quick``: ``{25, 50, 100}``), every path of
:mod:`benchmarks.bench_robust` (balustrade default, exact, long-horizon, cvxpy, fast-convex
when present, and the hand-written Clarabel baseline), timed interleaved on the same states.

The IPOPT paths (``exact``, ``long-horizon``) run only up to :data:`SLOW_MAX_N` (``N = 200``):
at ``N = 400`` one of their steps takes seconds to tens of seconds under load and the sweep
would not finish in 10 minutes; their exponent is fitted over the horizons they ran.

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
    PATHS,
    build_paths,
    closed_loop_states,
    measure,
    verify,
)

HORIZONS, QUICK_HORIZONS = (25, 50, 100, 200, 400), (25, 50, 100)
#: the IPOPT paths and the largest horizon they are timed at (module docstring)
SLOW, SLOW_MAX_N = ("exact", "long-horizon"), 200


def fitted_exponent(N: np.ndarray, t: np.ndarray) -> float:
    """``a`` of ``t ≈ c N^a``: the least-squares slope of ``log t`` against ``log N``."""
    N, t = np.asarray(N, dtype=float), np.asarray(t, dtype=float)
    keep = np.isfinite(t) & (t > 0)
    if keep.sum() < 2:
        return float("nan")
    slope, _ = np.polyfit(np.log(N[keep]), np.log(t[keep]), 1)
    return float(slope)


def sweep(horizons: tuple[int, ...], n_states: int, slow_max_n: int = SLOW_MAX_N
          ) -> tuple[dict, dict, list[dict]]:
    """``({(alg, label): {N: median}}, {label: reason not available}, rows per N)``; the
    :data:`SLOW` paths only for ``N <= slow_max_n``."""
    medians: dict = {}
    missing: dict = {}
    rows = []
    for N in horizons:
        d = design(N, 40)
        direct = DirectRendezvous(RendezvousData.from_design(d))
        states = closed_loop_states(d, direct, n_states + 1)
        names = tuple(k for k in PATHS if N <= slow_max_n or k not in SLOW)
        paths, missing = build_paths(d, names)
        times, checks = measure(d, states, paths, direct)
        verify(checks)
        for (alg, label), pt in times.items():
            st = pt.stats()
            medians.setdefault((alg, label), {})[N] = st["median_s"]
            rows.append({"name": f"horizon Alg {alg} N={N}: {label}", **st})
    return medians, missing, rows


def run(quick: bool = False) -> list[dict]:
    horizons = QUICK_HORIZONS if quick else HORIZONS
    medians, missing, rows = sweep(horizons, 3 if quick else 5)
    for (alg, label), by_n in medians.items():
        base = medians[(alg, BASELINE)]
        Ns = sorted(by_n)
        t = np.array([by_n[n] for n in Ns])
        rows.append({"name": f"horizon Alg {alg}: {label} t ∝ N^a",
                     "exponent": round(fitted_exponent(np.array(Ns), t), 2),
                     "N": Ns, "median_ms": [round(1e3 * float(v), 2) for v in t],
                     "x_handwritten": [round(float(by_n[n] / base[n]), 2) for n in Ns]})
    for label, reason in missing.items():
        rows.append({"name": f"horizon: {label}", "status": reason})
    return rows
