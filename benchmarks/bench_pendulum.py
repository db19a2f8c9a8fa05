"""Per-step time of the pendulum PCBF safety filter (both problems, (2.24) then (2.23)).

Compiled backends (CasADi sqpmethod/qrqp, CasADi IPOPT, cvxpy DPP) run the closed loop of
the demo; the naive baseline rebuilds both cvxpy problems from scratch at every step, as
the thesis' implementation did, and is timed on the same states in the same run.
"""

from __future__ import annotations

import time

import cvxpy as cp
import numpy as np

from balustrade.control import PCBFSafetyFilter, simulate
from balustrade.design.terminal_cbf import synthesize_terminal_cbf
from balustrade.models.pendulum import pendulum, pendulum_setup

RATES = (-1.5, -0.75, 0.0, 0.75, 1.5)


def rebuild_step(A, B, X, U, P, deltas, alpha_f, x, u_p, eps=1e-6) -> float:
    """Build and solve (2.24) and (2.23) from scratch with plain cvxpy; returns u_0."""
    n, m, N = A.shape[0], B.shape[1], len(deltas)
    xs, us = cp.Variable((n, N + 1)), cp.Variable((m, N))
    xi, xi_N = cp.Variable((X.H.shape[0], N), nonneg=True), cp.Variable(nonneg=True)
    base = [xs[:, 0] == x, xs[:, 1:] == A @ xs[:, :-1] + B @ us,
            U.H @ us <= U.h[:, None]]
    state = [X.H @ xs[:, i] - X.h + deltas[i] <= xi[:, i] for i in range(N)]
    term = [cp.quad_form(xs[:, N], P) - 1 <= xi_N]
    cp.Problem(cp.Minimize(alpha_f * xi_N + cp.sum(xi)), base + state + term).solve(
        solver="CLARABEL")
    xi_v, xi_N_v = np.maximum(xi.value, 0), max(float(xi_N.value), 0.0)
    xs2, us2 = cp.Variable((n, N + 1)), cp.Variable((m, N))
    base = [xs2[:, 0] == x, xs2[:, 1:] == A @ xs2[:, :-1] + B @ us2,
            U.H @ us2 <= U.h[:, None]]
    state = [X.H @ xs2[:, i] - X.h + deltas[i] <= xi_v[:, i] + eps for i in range(N)]
    term = [cp.quad_form(xs2[:, N], P) - 1 <= xi_N_v + eps]
    prob = cp.Problem(cp.Minimize(cp.sum_squares(us2[:, 0] - u_p)), base + state + term)
    prob.solve(solver="CLARABEL")
    return float(us2.value[0, 0])


def run(quick: bool = False) -> list[dict]:
    system, s = pendulum(), pendulum_setup()
    h_f = synthesize_terminal_cbf(system.A, system.B, s.X, s.U, delta_N=s.deltas[-1])
    steps = 40 if quick else 150
    rows, states = [], None
    # (backend, solver) labels of the rows -> the target behind them
    variants = {("casadi", "sqpmethod"): "fast-sqp", ("casadi", "ipopt"): "exact",
                ("cvxpy", None): "cvxpy"}
    medians = {}
    for (backend, solver), target in variants.items():
        ctl = PCBFSafetyFilter.build(system, s.X, s.U, h_f, s.N, s.deltas, s.alpha_f,
                                     target=target)
        times, visited = [], []
        for w0 in RATES:
            ctl.reset()
            trace = simulate(system, ctl, [0.0, w0], steps, proposal=2.0)
            times.extend(trace.step_times)
            visited.extend(trace.states[:-1])
        medians[(backend, solver)] = float(np.median(times))
        if states is None:
            states = np.array(visited)
    n_base = 15 if quick else 60
    idx = np.linspace(0, len(states) - 1, n_base).astype(int)
    base_times = []
    for x in states[idx]:
        start = time.perf_counter()
        rebuild_step(system.A, system.B, s.X, s.U, h_f.P, s.deltas, s.alpha_f, x, 2.0)
        base_times.append(time.perf_counter() - start)
    baseline = float(np.median(base_times))
    rows.append({"name": "pendulum PCBF step: cvxpy rebuilt every step (baseline)",
                 "median_s": baseline, "samples": len(base_times)})
    for (backend, solver), med in medians.items():
        rows.append({"name": f"pendulum PCBF step: {backend}/{solver or 'default'}",
                     "median_s": med, "baseline": "cvxpy rebuild", "ratio": baseline / med,
                     "samples": len(RATES) * steps})
    return rows
