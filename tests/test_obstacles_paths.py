"""The reproduction's bookkeeping of the exact PCBF reference loop (reproduce/obstacles.py):
certificate uses counted under both keys, and its own path labels."""

from __future__ import annotations

import numpy as np
import pytest

from balustrade.reproduce import obstacles as R


def test_certificate_counts_count_first_and_after_failed():
    """``certificate_first`` (the default: checked before (2.24)) and ``shifted_certificate``
    (after a failed (2.24)) are both counted, separately; NaN = key absent that step."""
    nan = np.nan
    values = {"certificate_first": np.array([nan, 1.0, 1.0, nan, 1.0]),
              "shifted_certificate": np.array([nan, nan, nan, 1.0, nan])}
    assert R.certificate_counts(values) == {"first": 3, "after_failed": 1}
    assert R.certificate_counts({}) == {"first": 0, "after_failed": 0}


def _run(statuses: list[str], classify) -> dict:
    n = len(statuses)
    return {"start": [-2.0, 0.5], "states": np.zeros((n + 1, 5)), "inputs": np.zeros((n, 2)),
            "statuses": statuses, "paths": [classify(s) for s in statuses],
            "solve_times": np.arange(1, n + 1) * 1e-3, "min_distance_per_obstacle": [0.1],
            "min_distance": 0.1, "changed": np.zeros(n, bool),
            "certificates": {"first": 2, "after_failed": 0}, "fallbacks": 0,
            "stopped": False}


def test_pcbf_loop_has_its_own_paths_and_summary():
    """The PCBF loop's "certified" steps are not Algorithm 7.5's "certified" path."""
    statuses = ["ok", "certified", "certified", "certified_filter_infeasible"]
    assert [R.pcbf_path_of(s) for s in statuses] == \
        ["pcbf_solved", "pcbf_certified", "pcbf_certified", "pcbf_other"]
    m = R.loop_metrics([_run(statuses, R.pcbf_path_of)], R.PCBF_PATHS)
    assert set(m["timing_ms"]) == set(R.PCBF_PATHS)
    assert m["timing_ms"]["pcbf_certified"] == {"n": 2, "median_ms": 2.5, "mean_ms": 2.5}
    assert m["paths"] == {"pcbf_solved": 1, "pcbf_certified": 2, "pcbf_other": 1}
    with pytest.raises(KeyError):   # 7.5's timings never take the PCBF loop's paths
        R.loop_metrics([_run(statuses, R.pcbf_path_of)])
    py = R.loop_metrics([_run(["certified", "ok"], R.path_of)])
    metrics = {"python": py, "pcbf": {"median_ms": 300.0},
               "pcbf_closed_loop": m}
    line = [s for s in R.summary_lines(metrics) if s.startswith("PCBF algorithm closed")][0]
    assert "used in 2/4 steps (2 checked first, 0 after a failed (2.24))" in line
