"""Trace.save / Trace.load round-trip a closed-loop run exactly (a tidy CSV table plus JSON
metadata), and Trace.plot draws states, inputs, proposals, values and fallbacks."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from balustrade.control import StepInfo, Trace, simulate
from balustrade.dsl import LinearSystem
from balustrade.errors import BalustradeError


class _Scripted:
    """Saturates the proposal; every third step reports a fallback and an uncertified solve,
    and records two values (one missing at some steps: NaN in the trace)."""

    def step(self, x, u_p):
        k = self.k = getattr(self, "k", -1) + 1
        info = StepInfo(status="optimal" if k % 3 else "max_iterations",
                        fallback=None if k % 3 else "shifted", solve_time=1e-4 * (k + 1))
        info.values["h"] = float(x @ x) / 3.0
        if k % 2:
            info.values["gap"] = 0.1 * k
        if k % 3 == 0:
            info.uncertified["filter"] = "max_iterations"
        return np.clip(u_p, -1.0, 1.0), info

    def reset(self):
        self.k = -1


def run(steps: int = 12) -> Trace:
    plant = LinearSystem([[1.0, 0.1], [0.0, 1.0]], [[0.0], [0.1]], np.eye(2), name="di")
    w = np.random.default_rng(3).normal(size=(steps, 2)) * 1e-2
    return simulate(plant, _Scripted(), [0.3, -0.2], steps,
                    proposal=lambda k, x: np.array([np.sin(k) * 2.0]), disturbance=w)


def assert_same(a: Trace, b: Trace) -> None:
    for field in ("states", "inputs", "proposed", "disturbances", "solve_times", "step_times"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=field)
    assert a.values.keys() == b.values.keys()
    for k in a.values:
        np.testing.assert_array_equal(a.values[k], b.values[k])  # NaN == NaN here
    assert a.statuses == b.statuses and a.fallbacks == b.fallbacks
    assert a.uncertified == b.uncertified and a.stopped == b.stopped


def test_save_load_round_trip(tmp_path):
    trace = run()
    assert np.isnan(trace.values["gap"][0])
    csv_path, json_path = trace.save(tmp_path / "runs" / "loop.csv")
    assert csv_path.name == "loop.csv" and json_path.name == "loop.json"
    assert_same(trace, Trace.load(tmp_path / "runs" / "loop"))
    assert_same(trace, Trace.load(json_path))
    # the table is tidy: a header and one row per sample (the last one: the final state)
    with csv_path.open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 13 and rows[-1]["u[0]"] == "" and rows[-1]["x[1]"] != ""
    assert rows[0]["fallback"] == "shifted" and rows[1]["fallback"] == ""
    assert json.loads(rows[0]["uncertified"]) == {"filter": "max_iterations"}
    meta = json.loads(json_path.read_text())
    assert meta["n_steps"] == 12 and set(meta["values"]) == {"h", "gap"}
    assert meta["fallback_steps"] == [0, 3, 6, 9]


def test_round_trip_of_a_stopped_run(tmp_path):
    unstable = LinearSystem([[1e7]], [[1.0]], name="boom")

    class Zero:
        def step(self, x, u_p):
            return np.zeros(1), StepInfo()

        def reset(self):
            pass

    trace = simulate(unstable, Zero(), [1.0], 5)
    assert trace.stopped and trace.states.shape[0] == trace.inputs.shape[0] + 1
    trace.save(tmp_path / "stopped")
    assert_same(trace, Trace.load(tmp_path / "stopped.csv"))


def test_load_errors(tmp_path):
    with pytest.raises(BalustradeError, match="cannot read"):
        Trace.load(tmp_path / "missing")
    (tmp_path / "other.json").write_text('{"format": "something"}')
    (tmp_path / "other.csv").write_text("k\n")
    with pytest.raises(BalustradeError, match="not a saved trace"):
        Trace.load(tmp_path / "other")


def test_load_of_edited_files_is_a_clear_error(tmp_path):
    """A metadata file without a key, or a table without a column, is a BalustradeError
    naming what is missing (it was a raw KeyError)."""
    run().save(tmp_path / "run")
    meta = json.loads((tmp_path / "run.json").read_text())
    del meta["nx"]
    (tmp_path / "run.json").write_text(json.dumps(meta))
    with pytest.raises(BalustradeError, match=r"lacks the keys \['nx'\]"):
        Trace.load(tmp_path / "run")
    run().save(tmp_path / "run2")
    with (tmp_path / "run2.csv").open() as fh:
        rows = list(csv.reader(fh))
    keep = [j for j, c in enumerate(rows[0]) if c != "x[0]"]
    with (tmp_path / "run2.csv").open("w", newline="") as fh:
        csv.writer(fh).writerows([[r[j] for j in keep] for r in rows])
    with pytest.raises(BalustradeError, match="does not match its metadata.*x\\[0\\]"):
        Trace.load(tmp_path / "run2")


def test_plot_draws_every_panel_and_saves(tmp_path):
    trace = run()
    fig = trace.plot(tmp_path / "loop.png", dt=0.1, state_names=["p", "v"], title="scripted")
    axes = fig.get_axes()
    assert len(axes) == 4  # states, inputs, values, events
    states, inputs, values, events = axes
    assert [ln.get_label() for ln in states.get_lines()] == ["p", "v"]
    labels = [ln.get_label() for ln in inputs.get_lines()]
    assert labels == ["u[0] applied", "u[0] proposed"]
    np.testing.assert_array_equal(inputs.get_lines()[1].get_ydata(), trace.proposed[:, 0])
    assert {ln.get_label() for ln in values.get_lines()} == {"h", "gap"}
    assert [t.get_text() for t in events.get_yticklabels()] == ["shifted", "uncertified"]
    assert "4 fallbacks" in fig._suptitle.get_text()
    png = tmp_path / "loop.png"
    assert png.exists() and png.read_bytes()[:4] == b"\x89PNG"
    with pytest.raises(BalustradeError, match="state_names"):
        trace.plot(state_names=["only one"])


def test_plot_without_values_or_fallbacks():
    plant = LinearSystem([[0.9]], [[1.0]], name="scalar")

    class Hold:
        def step(self, x, u_p):
            return u_p, StepInfo()

        def reset(self):
            pass

    fig = simulate(plant, Hold(), [1.0], 4).plot()
    assert len(fig.get_axes()) == 3  # states, inputs, events
