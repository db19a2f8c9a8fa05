"""Section 7.5 / Figure 7.1 (PCBF curves): the PCBF safety filter on the pendulum (7.10).

Proposed input ``u_p = 2`` from ``ψ₀ = 0`` and ``ω₀ ∈ {−1.5, −0.75, 0, 0.75, 1.5}`` for
150 steps; the filter solves (2.24) then (2.23) each step and applies ``u*_{0|k}``. Writes
``metrics.json`` (max constraint violation per run, ``h_PB`` and the extended ``h`` (7.7)
along each run, final states, median step time, ``γ_f``) and ``pendulum_pcbf.png`` (ψ, ω
and ``h`` over time, like Figure 7.1).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from balustrade.backends import compile
from balustrade.control import PCBFSafetyFilter, simulate
from balustrade.design.terminal_cbf import synthesize_terminal_cbf
from balustrade.models.pendulum import pendulum, pendulum_setup
from balustrade.problems.pcbf import combined_h, extended_pcbf_problem
from balustrade.reproduce._plotting import figure, save

NAMES = ("pendulum",)
INITIAL_RATES = (-1.5, -0.75, 0.0, 0.75, 1.5)
THESIS_GAMMA_F = 2.95


def run(out: Path, quick: bool = False, target: str = "fast-sqp") -> dict:
    """Run the five closed loops and write metrics and the plot into ``out``; every problem
    is compiled for ``target`` (a preset name, e.g. ``"cvxpy"``)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    system, setup = pendulum(), pendulum_setup()
    steps = 60 if quick else 150
    h_f = synthesize_terminal_cbf(system.A, system.B, setup.X, setup.U,
                                  delta_N=setup.deltas[-1])
    start = time.perf_counter()
    controller = PCBFSafetyFilter.build(system, setup.X, setup.U, h_f, setup.N, setup.deltas,
                                        setup.alpha_f, slack_norm=1, target=target)
    compile_time = time.perf_counter() - start
    extended = compile(extended_pcbf_problem(system, setup.X, setup.U, h_f, setup.N,
                                             setup.deltas), target)
    runs = []
    for omega0 in INITIAL_RATES:
        controller.reset()
        trace = simulate(system, controller, [0.0, omega0], steps, proposal=2.0)
        c = trace.states @ setup.X.H.T - setup.X.h
        h = trace.values["h_PB"]
        inside = np.flatnonzero(h <= 1e-6)
        h_ext = [combined_h(hp, extended.solve({"x0": x}).objective)
                 for hp, x in zip(h, trace.states)]
        runs.append({
            "omega0": omega0,
            "max_violation": float(max(np.max(c), 0.0)),
            "max_violation_in_S_PB": float(max(np.max(c[inside[0]:]), 0.0)) if inside.size
            else None,
            "h_PB": h.tolist(),
            "h": h_ext,
            "final_state": trace.states[-1].tolist(),
            "median_step_s": float(np.median(trace.step_times)),
            "fallbacks": trace.n_fallbacks,
            "states": trace.states.tolist(),
            "inputs": trace.inputs[:, 0].tolist(),
        })
    metrics = {
        "example": "thesis Section 7.5, Figure 7.1 (PCBF algorithm)",
        "target": target,
        "steps": steps,
        "gamma_f": h_f.gamma_f,
        "gamma_f_thesis": THESIS_GAMMA_F,
        "P": h_f.P.tolist(),
        "K": h_f.K.tolist(),
        "compile_s": compile_time,
        "median_step_s": float(np.median([r["median_step_s"] for r in runs])),
        "runs": runs,
    }
    metrics["plots"] = [_plot(runs, setup, out / "pendulum_pcbf.png")]
    metrics["summary_table"] = _table(metrics)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=1))
    return metrics


def _table(m: dict) -> str:
    lines = [
        "Pendulum PCBF safety filter (thesis Sec. 7.5, Fig. 7.1), u_p = 2, "
        f"{m['steps']} steps, target {m['target']}",
        f"gamma_f = {m['gamma_f']:.3f} (thesis reports 2.95; K of (7.11) is not unique, "
        "see docs/pendulum.md)",
        f"{'omega0':>7} {'max viol.':>10} {'viol. in S_PB':>14} {'final psi':>10} "
        f"{'final omega':>12} {'h_PB(0)':>8} {'fallbacks':>9} {'step [ms]':>9}",
    ]
    for r in m["runs"]:
        vin = r["max_violation_in_S_PB"]
        lines.append(f"{r['omega0']:>7.2f} {r['max_violation']:>10.2e} "
                     f"{(f'{vin:.2e}' if vin is not None else 'never'):>14} "
                     f"{r['final_state'][0]:>10.4f} {r['final_state'][1]:>12.2e} "
                     f"{r['h_PB'][0]:>8.3f} {r['fallbacks']:>9d} "
                     f"{r['median_step_s'] * 1e3:>9.3f}")
    lines.append(f"median step time (both problems): {m['median_step_s'] * 1e3:.3f} ms "
                 "(thesis: 21 ms with CVXPY rebuilt per step)")
    return "\n".join(lines)


def _plot(runs: list[dict], setup, path: Path) -> str:
    fig, axes = figure(3, 1, (7.0, 7.5))
    for r in runs:
        x = np.array(r["states"])
        k = np.arange(len(x))
        label = f"ω₀ = {r['omega0']:+.2f}"
        axes[0].plot(k, x[:, 0], label=label)
        axes[1].plot(k, x[:, 1])
        axes[2].plot(np.arange(len(r["h"])), r["h"])
    axes[0].axhline(setup.X.h[0], color="k", ls="--", lw=1)
    axes[1].axhline(setup.X.h[1], color="k", ls="--", lw=1)
    axes[1].axhline(-setup.X.h[3], color="k", ls="--", lw=1)
    axes[0].set_ylabel("ψ [rad]")
    axes[1].set_ylabel("ω [rad/s]")
    axes[2].axhline(0.0, color="k", ls="--", lw=1)
    axes[2].set_ylabel("h (7.7)")
    axes[2].set_xlabel("step k")
    axes[0].legend(fontsize=8, ncol=3)
    axes[0].set_title("PCBF safety filter, pendulum (7.10), u_p = 2")
    return save(fig, path)
