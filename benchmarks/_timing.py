"""Timing helpers shared by the benchmarks (ratios measured in the same run)."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable

import numpy as np


def interleaved(fns: dict[str, Callable], items: Iterable, repeat: int = 1,
                block: int = 10) -> dict[str, float]:
    """Median time per call of each function, the functions taking turns on blocks of
    ``block`` items: a load change on the shared machine hits all of them alike (ratios of the
    same run), while each keeps its caches warm within a block."""
    times: dict[str, list[float]] = {k: [] for k in fns}
    items = list(items)
    for _ in range(repeat):
        for i in range(0, len(items), block):
            for k, fn in fns.items():
                for item in items[i:i + block]:
                    t0 = time.perf_counter()
                    fn(item)
                    times[k].append(time.perf_counter() - t0)
    return {k: float(np.median(v)) for k, v in times.items()}
