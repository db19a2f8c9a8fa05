"""Per-step time of the rendezvous safety filters (thesis Section 6.5): Algorithm 5.2 (two
problems, (5.15) then (5.16)) and Algorithm 6.4 (one problem, (6.15)) at ``N = 200``.

Compiled variants (built once, re-solved with new parameters): CasADi + IPOPT and cvxpy (DPP,
Clarabel). The baseline rebuilds the cvxpy problems from scratch at every step, as the thesis'
CVXPY implementation did, timed on the same states in the same run. The thesis reports
234 ms (5.2) and 148 ms (6.4) per step (CVXPY + MOSEK, i7-10510U); ``vs_thesis`` is that
time divided by ours. ``quick`` uses ``N = 30``.
"""

from __future__ import annotations

import time

import cvxpy as cp
import numpy as np

from balustrade.reproduce.rendezvous import closed_loop, controllers, design

THESIS_S = {"5.2": 0.234, "6.4": 0.148}


def _common(d: dict, z, v) -> list:
    system, s, error = d["system"], d["setup"], d["error"]
    X_E, U_E = error.tighten_state(s.X), error.tighten_input(s.U)
    cons = [z[:, 1:] == system.A @ z[:, :-1] + system.B @ v,
            U_E.H @ v <= U_E.h[:, None]]
    return cons, X_E


def rebuild_alg52(d: dict, x: np.ndarray) -> np.ndarray:
    """(5.15) and (5.16) built from scratch with plain cvxpy; returns the applied input."""
    s, error, cbf = d["setup"], d["error"], d["cbf"]
    n, m, N = 6, 3, s.N
    deltas = s.deltas()
    Pe = error.E.P
    z, v = cp.Variable((n, N + 1)), cp.Variable((m, N))
    cons, X_E = _common(d, z, v)
    xi, xi_N = cp.Variable((X_E.n_rows, N), nonneg=True), cp.Variable(nonneg=True)
    tube = [cp.quad_form(x - z[:, 0], Pe) <= 1]
    state = [X_E.H @ z[:, :N] - X_E.h[:, None] + deltas[None, :] <= xi]
    term = [cp.quad_form(z[:, N], cbf.P) - 1 <= xi_N]
    cp.Problem(cp.Minimize(s.alpha_f * xi_N + cp.sum(xi)), cons + tube + state + term).solve(
        solver="CLARABEL")
    xi_v, xi_N_v = np.maximum(xi.value, 0), max(float(xi_N.value), 0.0)
    z2, v2 = cp.Variable((n, N + 1)), cp.Variable((m, N))
    cons2, _ = _common(d, z2, v2)
    tube2 = [cp.quad_form(x - z2[:, 0], Pe) <= 1]
    state2 = [X_E.H @ z2[:, :N] - X_E.h[:, None] + deltas[None, :] <= xi_v + 1e-6]
    term2 = [cp.quad_form(z2[:, N], cbf.P) - 1 <= xi_N_v + 1e-6]
    cp.Problem(cp.Minimize(cp.sum(cp.abs(v2))), cons2 + tube2 + state2 + term2).solve(
        solver="CLARABEL")
    return v2.value[:, 0] + error.K @ (x - z2.value[:, 0])


def rebuild_alg64(d: dict, x: np.ndarray, bound: float) -> np.ndarray:
    """(6.15) built from scratch with plain cvxpy; returns the applied input."""
    s, error, cbf = d["setup"], d["error"], d["cbf"]
    n, m, N = 6, 3, s.N
    deltas = s.deltas()
    z, v = cp.Variable((n, N + 1)), cp.Variable((m, N))
    cons, X_E = _common(d, z, v)
    xi, xi_N = cp.Variable((X_E.n_rows, N), nonneg=True), cp.Variable(nonneg=True)
    cons += [cp.quad_form(x - z[:, 0], error.E.P) <= 1,
             X_E.H @ z[:, :N] - X_E.h[:, None] + deltas[None, :] <= xi,
             cp.quad_form(z[:, N], cbf.P) - 1 <= xi_N,
             s.alpha_f * xi_N + cp.sum(xi) <= bound]
    cp.Problem(cp.Minimize(cp.sum(cp.abs(v))), cons).solve(solver="CLARABEL")
    return v.value[:, 0] + error.K @ (x - z.value[:, 0])


def _timed_steps(ctl, states: np.ndarray) -> list[float]:
    """Wall time of ``ctl.step`` along recorded states (the controller keeps its own warm
    starts and candidates as in the closed loop)."""
    ctl.reset()
    times = []
    for x in states:
        start = time.perf_counter()
        ctl.step(x, np.zeros(3))
        times.append(time.perf_counter() - start)
    return times


def run(quick: bool = False) -> list[dict]:
    N, T = (30, 40) if quick else (200, 40)
    n_timed = 10 if quick else 12
    d = design(N, T)
    rows = []
    compiled = {b: controllers(d, (0.9,), target=None if b == "casadi" else b,
                              record_h_r=False)
                for b in ("casadi", "cvxpy")}
    # states of one disturbed closed loop of Algorithm 5.2 (CasADi): the operating points
    loop = closed_loop(compiled["casadi"]["robust"], d, disturbed=True)
    states = loop["states"][:n_timed]
    medians = {}
    for backend, ctls in compiled.items():
        for alg, key in (("5.2", "robust"), ("6.4", "mo_rho0.9")):
            medians[(alg, backend)] = float(np.median(_timed_steps(ctls[key], states)))
    base52, base64 = [], []
    mo = compiled["casadi"]["mo_rho0.9"]
    mo.reset()
    for x in states[: max(3, n_timed // 2)]:
        start = time.perf_counter()
        rebuild_alg52(d, x)
        base52.append(time.perf_counter() - start)
        _, info = mo.step(x, np.zeros(3))  # the loop's bound (6.15g) at this state
        bound = info.values["bound"] + 1e-6
        start = time.perf_counter()
        rebuild_alg64(d, x, bound)
        base64.append(time.perf_counter() - start)
    baselines = {"5.2": float(np.median(base52)), "6.4": float(np.median(base64))}
    for alg in ("5.2", "6.4"):
        rows.append({"name": f"rendezvous Alg {alg} N={N}: cvxpy rebuilt every step (baseline)",
                     "median_s": baselines[alg], "samples": len(base52),
                     "vs_thesis": round(THESIS_S[alg] / baselines[alg], 2)})
        for backend in ("casadi", "cvxpy"):
            med = medians[(alg, backend)]
            rows.append({"name": f"rendezvous Alg {alg} N={N}: {backend} compiled",
                         "median_s": med, "baseline": "cvxpy rebuild",
                         "ratio": baselines[alg] / med, "samples": len(states),
                         "thesis_ms": THESIS_S[alg] * 1e3,
                         "vs_thesis": round(THESIS_S[alg] / med, 2)})
    return rows
