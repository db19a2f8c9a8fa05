"""Looking at and keeping closed-loop runs: :meth:`Trace.plot`, :meth:`Trace.save`,
:meth:`Trace.load` (issue #13 §7).

Saved runs are a tidy table and its metadata, side by side:

* ``run.csv`` — one row per sample ``k``: the state ``x[i]`` at ``k``, the applied input
  ``u[i]``, the proposal ``u_p[i]``, the disturbance ``w[i]``, each recorded value
  ``value[name]`` (e.g. the PCBF value functions), ``status``, ``fallback``, ``solve_time``,
  ``step_time`` and ``uncertified`` (a JSON object); the last row holds the final state only
  (empty cells). Numbers are written with ``repr``, so a load gives back the same floats;
  readable by any spreadsheet or ``pandas.read_csv``.
* ``run.json`` — the metadata: dimensions, number of states and steps, why the run stopped,
  the value names, the column names.

:attr:`Trace.infos` (per-step solver solutions) is not saved. Plots are drawn on a
:class:`matplotlib.figure.Figure` without pyplot (no GUI backend, no global state; saving
uses Agg): states, applied versus proposed inputs, the recorded values, and the steps where
a fallback was used or a solve was not certified optimal.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from balustrade.errors import BalustradeError

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from balustrade.control.base import Trace

FORMAT, VERSION = "balustrade.trace", 1


# -- saving --------------------------------------------------------------------------
def _paths(path: str | Path) -> tuple[Path, Path]:
    path = Path(path)
    if path.suffix in (".csv", ".json"):
        path = path.with_suffix("")
    return path.with_suffix(".csv"), path.with_suffix(".json")


def _columns(trace: Trace) -> dict[str, list[str]]:
    nx, nu, nw = trace.states.shape[1], trace.inputs.shape[1], trace.disturbances.shape[1]
    return {"x": [f"x[{i}]" for i in range(nx)], "u": [f"u[{i}]" for i in range(nu)],
            "u_p": [f"u_p[{i}]" for i in range(nu)], "w": [f"w[{i}]" for i in range(nw)],
            "value": [f"value[{name}]" for name in trace.values]}


def _num(v: float) -> str:
    return repr(float(v))


def save_trace(trace: Trace, path: str | Path) -> tuple[Path, Path]:
    """Write ``<path>.csv`` (one row per sample) and ``<path>.json`` (metadata); ``path`` may
    end in ``.csv``, ``.json`` or nothing. Returns both paths."""
    csv_path, json_path = _paths(path)
    cols = _columns(trace)
    n_states, n_steps = trace.states.shape[0], trace.inputs.shape[0]
    header = (["k"] + cols["x"] + cols["u"] + cols["u_p"] + cols["w"] + cols["value"]
              + ["status", "fallback", "solve_time", "step_time", "uncertified"])
    csv_path.parent.mkdir(parents=True, exist_ok=True)
    with csv_path.open("w", newline="") as fh:
        out = csv.writer(fh)
        out.writerow(header)
        for k in range(max(n_states, n_steps)):
            row = [str(k)]
            row += [_num(v) for v in trace.states[k]] if k < n_states else [""] * len(cols["x"])
            if k < n_steps:
                row += [_num(v) for v in trace.inputs[k]] + [_num(v) for v in trace.proposed[k]]
                row += [_num(v) for v in trace.disturbances[k]]
                row += [_num(trace.values[name][k]) for name in trace.values]
                fallback = trace.fallbacks[k]
                uncertified = trace.uncertified[k] if k < len(trace.uncertified) else {}
                row += [trace.statuses[k], "" if fallback is None else fallback,
                        _num(trace.solve_times[k]), _num(trace.step_times[k]),
                        json.dumps(uncertified, sort_keys=True)]
            else:
                row += [""] * (len(header) - len(row))
            out.writerow(row)
    meta = {"format": FORMAT, "version": VERSION, "csv": csv_path.name,
            "nx": len(cols["x"]), "nu": len(cols["u"]), "nw": len(cols["w"]),
            "n_states": n_states, "n_steps": n_steps, "stopped": trace.stopped,
            "values": list(trace.values), "columns": header,
            "fallback_steps": [k for k, f in enumerate(trace.fallbacks) if f is not None]}
    json_path.write_text(json.dumps(meta, indent=2) + "\n")
    return csv_path, json_path


def load_trace(path: str | Path) -> Trace:
    """Read a run written by :func:`save_trace` (``path`` with or without a suffix)."""

    csv_path, json_path = _paths(path)
    try:
        meta = json.loads(json_path.read_text())
        with csv_path.open(newline="") as fh:
            rows = list(csv.DictReader(fh))
    except (OSError, ValueError) as exc:
        raise BalustradeError(f"Trace.load({path}): cannot read {csv_path.name} and "
                              f"{json_path.name}: {exc}") from exc
    if meta.get("format") != FORMAT:
        raise BalustradeError(f"Trace.load({path}): {json_path.name} is not a saved trace "
                              f"(format {meta.get('format')!r}, expected {FORMAT!r})")
    missing = [k for k in ("n_states", "n_steps", "nx", "nu", "nw", "values", "stopped")
               if k not in meta]
    if missing:
        raise BalustradeError(f"Trace.load({path}): {json_path.name} lacks the keys {missing}")
    try:
        return _trace_from(meta, rows, path, csv_path.name)
    except (KeyError, ValueError, TypeError) as exc:
        raise BalustradeError(f"Trace.load({path}): {csv_path.name} does not match its "
                              f"metadata ({type(exc).__name__}: {exc})") from exc


def _trace_from(meta: dict, rows: list[dict], path: str | Path, csv_name: str) -> Trace:
    """The :class:`Trace` of a saved run's metadata and per-step rows."""
    from balustrade.control.base import Trace

    n_states, n_steps = int(meta["n_states"]), int(meta["n_steps"])
    if len(rows) != max(n_states, n_steps):
        raise BalustradeError(f"Trace.load({path}): {csv_name} has {len(rows)} rows, the "
                              f"metadata says {max(n_states, n_steps)}")

    def table(names: list[str], n: int) -> np.ndarray:
        return np.array([[float(rows[k][c]) for c in names] for k in range(n)],
                        dtype=float).reshape(n, len(names))

    nx, nu, nw = int(meta["nx"]), int(meta["nu"]), int(meta["nw"])
    steps = rows[:n_steps]
    return Trace(
        states=table([f"x[{i}]" for i in range(nx)], n_states),
        inputs=table([f"u[{i}]" for i in range(nu)], n_steps),
        proposed=table([f"u_p[{i}]" for i in range(nu)], n_steps),
        disturbances=table([f"w[{i}]" for i in range(nw)], n_steps),
        values={name: np.array([float(r[f"value[{name}]"]) for r in steps])
                for name in meta["values"]},
        statuses=[r["status"] for r in steps],
        fallbacks=[r["fallback"] or None for r in steps],
        solve_times=np.array([float(r["solve_time"]) for r in steps]),
        step_times=np.array([float(r["step_time"]) for r in steps]),
        stopped=meta["stopped"],
        uncertified=[json.loads(r["uncertified"]) for r in steps])


# -- plotting ------------------------------------------------------------------------
def plot_trace(trace: Trace, path: str | Path | None = None, dt: float | None = None,
               state_names: list[str] | None = None, input_names: list[str] | None = None,
               title: str | None = None) -> Figure:
    """A figure of the run: states; applied (solid) and proposed (dashed) inputs; the
    recorded values (one axis, if any); and an event strip marking each step's fallback
    and the steps whose solves were not certified optimal (also shaded on every axis).
    ``dt`` puts time instead of the step on the horizontal axis; ``path`` saves the figure
    (format from the suffix). Returns the :class:`~matplotlib.figure.Figure`."""
    from matplotlib.figure import Figure

    nx, nu = trace.states.shape[1], trace.inputs.shape[1]
    state_names = _names(state_names, nx, "x", "state_names")
    input_names = _names(input_names, nu, "u", "input_names")
    scale = 1.0 if dt is None else float(dt)
    t_x = np.arange(trace.states.shape[0]) * scale
    t_u = np.arange(trace.inputs.shape[0]) * scale
    panels = ["states", "inputs"] + (["values"] if trace.values else []) + ["events"]
    ratios = [3, 3] + ([3] if trace.values else []) + [1.4]
    fig = Figure(figsize=(8.0, 2.2 * sum(ratios) / 3 + 0.8), layout="constrained")
    axes = dict(zip(panels, fig.subplots(len(panels), 1, sharex=True,
                                         gridspec_kw={"height_ratios": ratios})))
    for i in range(nx):
        axes["states"].plot(t_x, trace.states[:, i], label=state_names[i])
    axes["states"].set_ylabel("state")
    for i in range(nu):
        line, = axes["inputs"].step(t_u, trace.inputs[:, i], where="post",
                                    label=f"{input_names[i]} applied")
        axes["inputs"].step(t_u, trace.proposed[:, i], where="post", linestyle="--",
                            color=line.get_color(), alpha=0.6,
                            label=f"{input_names[i]} proposed")
    axes["inputs"].set_ylabel("input")
    if trace.values:
        for name, v in trace.values.items():
            axes["values"].plot(t_u, v, marker=".", markersize=3, label=name)
        axes["values"].set_ylabel("value")
    _events(axes["events"], trace, t_u)
    fallback_steps = [k for k, f in enumerate(trace.fallbacks) if f is not None]
    for name in panels[:-1]:
        for k in fallback_steps:
            axes[name].axvspan(t_u[k] - 0.5 * scale, t_u[k] + 0.5 * scale, color="tab:red",
                               alpha=0.12, linewidth=0)
        axes[name].legend(loc="best", fontsize="small")
        axes[name].grid(alpha=0.3)
    axes["events"].set_xlabel("step k" if dt is None else "time [s]")
    n_fb, n_unc, n_tr = trace.n_fallbacks, trace.n_uncertified, trace.n_truncated
    fig.suptitle((title + ": " if title else "") + f"{trace.inputs.shape[0]} steps, "
                 f"{n_fb} fallbacks, {n_unc} uncertified"
                 + (f", {n_tr} truncated" if n_tr else "")
                 + (f", stopped: {trace.stopped}" if trace.stopped else ""))
    if path is not None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=120)
    return fig


def _events(ax: object, trace: Trace, t: np.ndarray) -> None:
    """One row per fallback kind (red), one for uncertified solves (orange) and, when a
    solve was stopped by its budget (real-time mode), one for truncated steps (purple)."""
    kinds = sorted({f for f in trace.fallbacks if f is not None})
    truncated = trace.truncated_steps
    rows = kinds + ["uncertified"] + (["truncated"] if truncated else [])
    for y, kind in enumerate(kinds):
        ks = [k for k, f in enumerate(trace.fallbacks) if f == kind]
        ax.scatter(t[ks], [y] * len(ks), marker="|", s=120, color="tab:red")
    unc = [k for k, u in enumerate(trace.uncertified) if u]
    ax.scatter(t[unc], [len(kinds)] * len(unc), marker="|", s=120, color="tab:orange")
    if truncated:
        ax.scatter(t[truncated], [len(kinds) + 1] * len(truncated), marker="|", s=120,
                   color="tab:purple")
    ax.set_yticks(range(len(rows)), rows, fontsize="small")
    ax.set_ylim(-0.7, len(rows) - 0.3)
    statuses = sorted(set(trace.statuses))
    ax.set_title("statuses: " + ", ".join(f"{s} ×{trace.statuses.count(s)}" for s in statuses),
                 fontsize="small", loc="left")


def _names(names: list[str] | None, n: int, base: str, what: str) -> list[str]:
    if names is None:
        return [f"{base}[{i}]" for i in range(n)]
    names = [str(s) for s in names]
    if len(names) != n:
        raise BalustradeError(f"Trace.plot: {what} has {len(names)} names for {n} entries")
    return names

