"""The §8.3 reproduction's safety metrics and path labels (session 13, audit findings 2 and
6): ``safe`` covers every row of X — the discs and ``|δ| <= 0.75`` — and a step whose
filter applied a fallback is counted as ``fallback``, never as ``both_solves``."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from balustrade.reproduce import obstacles as R


def _states(delta_peak: float, n: int = 6) -> np.ndarray:
    """A straight run at y = −1.4 (over 0.4 m from every disc) with δ peaking."""
    S = np.zeros((n, 5))
    S[:, 0] = np.linspace(-1.5, 1.5, n)
    S[:, 1] = -1.4
    S[:, 3] = 3.0
    S[n // 2, 4] = delta_peak
    return S


def _run(states: np.ndarray) -> dict:
    n = len(states) - 1
    d = R.signed_distance(states, R.obstacle_setup().obstacles)
    return {"start": [0.8, 1.5], "states": states, "inputs": np.zeros((n, 2)),
            "statuses": ["certified"] * n, "paths": ["certified"] * n,
            "solve_times": np.full(n, 1e-3), "min_distance_per_obstacle": d.min(axis=0),
            "min_distance": float(d.min()), "changed": np.zeros(n, bool),
            "certificates": {"first": 0, "after_failed": 0}, "fallbacks": 0,
            "stopped": None}


def test_a_run_breaking_the_steering_bound_is_not_safe():
    """The auditor's quick run (0.8, 1.5): every disc kept, |δ| = 1.029 > 0.75."""
    bad = R.loop_metrics([_run(_states(1.029))])
    run = bad["runs"]["(0.8, 1.5)"]
    assert run["min_signed_distance"] > 0.4                # far from every disc
    assert run["state_constraints"]["max_abs_delta"] == pytest.approx(1.029)
    assert run["state_constraints"]["worst_per_row"][-2] == pytest.approx(1.029 - 0.75)
    assert len(run["state_constraints"]["worst_per_row"]) == 9 + 2
    assert not run["safe"] and not bad["all_safe"]
    assert bad["worst_other_state_row"] == pytest.approx(0.279)
    assert "VIOLATED" in R.summary_lines({"python": bad, "pcbf": {"median_ms": 1.0}})[0]
    neg = R.loop_metrics([_run(_states(-0.80))])         # the lower row, too
    assert not neg["all_safe"] and neg["runs"]["(0.8, 1.5)"]["state_constraints"][
        "worst_per_row"][-1] == pytest.approx(0.05)
    good = R.loop_metrics([_run(_states(0.72))])          # the exact PCBF's 0.72
    assert good["all_safe"] and good["runs"]["(0.8, 1.5)"]["safe"]
    assert good["worst_other_state_row"] == pytest.approx(-0.03)


def test_state_rows_are_the_rows_of_X():
    s = R.obstacle_setup()
    x = np.array([s.obstacles[4][0], s.obstacles[4][1], 0.0, 0.0, 0.5])   # disc centre
    rows = R.state_rows(x[None, :], s)[0]
    assert rows[4] == pytest.approx(s.obstacles[4][2] ** 2)
    assert rows[-2:] == pytest.approx([0.5 - 0.75, -0.5 - 0.75])


def test_a_fallback_step_is_not_both_solves():
    assert R.path_of("filter_failed", "max_decrease_solution") == "fallback"
    assert R.path_of("max_decrease_failed", "grid_minimizer") == "fallback"
    assert R.path_of("filter_feasible") == "both_solves"   # merely feasible (7.5), no fallback
    assert R.path_of("ok", None) == "both_solves"
    assert R.path_of("certified", None) == "certified"


def test_closed_loops_classify_by_the_recorded_fallback(monkeypatch):
    """closed_loops hands each step's ``StepInfo.fallback`` (Trace.fallbacks) to the path
    label: two ``filter_failed`` steps, one a fallback, get different paths."""
    statuses = ["certified", "filter_failed", "filter_failed", "ok"]
    fallbacks = [None, "max_decrease_solution", None, None]
    S = _states(0.0, len(statuses) + 1)

    def fake_simulate(system, filt, x0, steps, proposal):
        n = len(statuses)
        return SimpleNamespace(states=S, inputs=np.zeros((n, 2)), proposed=np.zeros((n, 2)),
                               statuses=statuses, fallbacks=fallbacks,
                               solve_times=np.full(n, 1e-3), values={},
                               n_fallbacks=1, stopped=None)

    monkeypatch.setattr(R, "simulate", fake_simulate)
    mpc = SimpleNamespace(start=lambda x0: None)
    filt = SimpleNamespace(reset=lambda: None)
    runs = R.closed_loops(filt, mpc, starts=((0.8, 1.5),), steps=len(statuses))
    assert runs[0]["paths"] == ["certified", "fallback", "both_solves", "both_solves"]
    m = R.loop_metrics(runs)
    assert m["paths"] == {"certified": 1, "fallback": 1, "both_solves": 2}
