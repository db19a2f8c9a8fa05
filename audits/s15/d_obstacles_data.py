"""Audit D: a small Algorithm 7.6 chunk of the §8.3 data (N = 50, Δ_j = j·1e-4, v_N = 0), then
(a) h of good rows outside S_PB recomputed with an own casadi Opti (2.24) (∞-norm slack, as the
project's default), multi-start; (b) dropped rows: own multi-start feasibility search."""
import os

os.makedirs("/tmp/audit_d", exist_ok=True)  # scratch files of the audit D scripts
import pickle
import sys
import time

import casadi as ca
import numpy as np

from balustrade.learn.sampler import Chunk, ProblemSpec, run_chunk

t0 = time.time()
spec = ProblemSpec.of("obstacles", target="exact")
rng = np.random.default_rng(int(sys.argv[1]) if len(sys.argv) > 1 else 3)
lb = np.array([-2, -1.5, -np.pi - 0.5, 0, -0.75]); ub = -lb; ub[3] = 4
goals = rng.uniform(lb, ub, (int(sys.argv[3]) if len(sys.argv) > 3 else 3, 5))
chunk = Chunk(0, "geometric", goals, seed=5, step=0.1, x_seed=(-0.4, -0.4, 0.0, 0.5, 0.0))
cols = run_chunk(spec, chunk)
print("sampled", len(cols["h"]), "rows in", time.time() - t0, "s; dropped", int((~cols["ok"]).sum()),
      "reasons", set(cols["reason"][~cols["ok"]]))
pickle.dump(cols, open(f"/tmp/audit_d/obst_chunk_{sys.argv[1]}.pkl" if len(sys.argv) > 1 else "/tmp/audit_d/obst_chunk.pkl", "wb"))
X = np.column_stack([cols[f"x{j}"] for j in range(5)])

TS, L, N = 0.02, 0.09, 50
obs = [(ox, oy, 0.15) for ox in (-0.8, 0, 0.8) for oy in (-0.8, 0, 0.8)]
def f(x, u):
    return ca.vertcat(x[0] + TS * x[3] * ca.cos(x[2]), x[1] + TS * x[3] * ca.sin(x[2]),
                      x[2] + TS * x[3] / L * ca.tan(x[4]), x[3] + TS * u[0], x[4] + TS * u[1])
def cx(x):
    return ca.vertcat(*[r ** 2 - (x[0] - ox) ** 2 - (x[1] - oy) ** 2 for ox, oy, r in obs],
                      x[4] - 0.75, -x[4] - 0.75)
def build(feas_only):
    o = ca.Opti()
    Z, U, S = o.variable(5, N + 1), o.variable(2, N), o.variable(1, N)
    p = o.parameter(5)
    o.subject_to(Z[:, 0] == p)
    for i in range(N):
        o.subject_to(Z[:, i + 1] == f(Z[:, i], U[:, i]))
        o.subject_to(o.bounded(ca.DM([-5, -2.8]), U[:, i], ca.DM([2, 2.8])))
        if not feas_only:
            o.subject_to(cx(Z[:, i]) + 1e-4 * i <= S[0, i])
    o.subject_to(S >= 0)
    o.subject_to(Z[3, N] == 0)
    o.subject_to(cx(Z[:, N]) + 1e-4 * N <= 0)
    o.minimize(ca.sum2(S) if not feas_only else ca.sumsqr(U) * 1e-6)
    o.solver("ipopt", {"print_time": False}, {"print_level": 0, "sb": "yes", "max_iter": 2000,
                                              "tol": 1e-8})
    return o, Z, U, S, p
def rollout(x, tau, dd):
    z = np.zeros((5, N + 1)); z[:, 0] = x
    for i in range(N):
        z[:, i + 1] = np.array(f(z[:, i], [tau[i], dd[i]])).reshape(-1)
    return z
def starts(x, k=6):
    out = []
    for j in range(k):
        # brake to v_N = 0 over a random number of steps, random constant steering rate
        n = rng.integers(max(1, int(np.ceil(x[3] / 5 / TS))), N + 1)
        tau = np.r_[np.full(n, -x[3] / (n * TS)), np.zeros(N - n)]
        dd = np.full(N, rng.uniform(-2.8, 2.8)) if j else np.zeros(N)
        out.append((rollout(x, tau, dd), np.vstack([tau, dd])))
    return out
def solve(o, Z, U, S, p, x, g):
    o.set_value(p, x); o.set_initial(Z, g[0]); o.set_initial(U, g[1]); o.set_initial(S, 0.1)
    try:
        s = o.solve()
        z = s.value(Z)
        rows = np.array([[float(v) for v in np.array(ca.evalf(cx(ca.DM(z[:, i])))).reshape(-1)] for i in range(N)])
        h = float(np.max(np.maximum(rows + 1e-4 * np.arange(N)[:, None], 0), axis=1).sum())
        return h
    except RuntimeError:
        return np.nan
slack = build(False)
feas = build(True)
good = np.flatnonzero(cols["ok"] & ~cols["in_s"])
pick = good[np.linspace(0, len(good) - 1, min(int(sys.argv[2]) if len(sys.argv) > 2 else 12, len(good))).round().astype(int)] if len(good) else []
for i in pick:
    vals = [solve(*slack, X[i], g) for g in starts(X[i])]
    print(f"row {i}: project h={cols['h'][i]:.6e}  own min={np.nanmin(vals) if np.any(np.isfinite(vals)) else np.nan:.6e}  "
          f"({np.sum(np.isfinite(vals))}/6 conv)")
for i in np.flatnonzero(~cols["ok"]):
    vals = [solve(*feas, X[i], g) for g in starts(X[i], 8)]
    print(f"dropped row {i} x={np.round(X[i], 3)} reason {cols['reason'][i]!r}: own feasible starts "
          f"{int(np.sum(np.isfinite(vals)))}/8")
print("total", time.time() - t0)
