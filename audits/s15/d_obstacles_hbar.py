"""Audit D: labels on S_PB (c_h · h̄_PB of (7.8), negative) of a sampled chunk, recomputed with
an own multi-start Opti (7.8): min t s.t. c_x(x_i) + Δ_i <= t (i < N), v_N = 0, c_x(x_N) + Δ_N <= 0."""
import pickle
import sys

import casadi as ca
import numpy as np

cols = pickle.load(open(sys.argv[1], "rb"))
X = np.column_stack([cols[f"x{j}"] for j in range(5)])
ins = np.flatnonzero(cols["ok"] & cols["in_s"])
pick = ins[np.linspace(0, len(ins) - 1, int(sys.argv[2])).round().astype(int)]
TS, L, N = 0.02, 0.09, 50
obs = [(ox, oy, 0.15) for ox in (-0.8, 0, 0.8) for oy in (-0.8, 0, 0.8)]
def f(x, u):
    return ca.vertcat(x[0] + TS * x[3] * ca.cos(x[2]), x[1] + TS * x[3] * ca.sin(x[2]),
                      x[2] + TS * x[3] / L * ca.tan(x[4]), x[3] + TS * u[0], x[4] + TS * u[1])
def cx(x):
    return ca.vertcat(*[q ** 2 - (x[0] - ox) ** 2 - (x[1] - oy) ** 2 for ox, oy, q in obs], x[4] - 0.75, -x[4] - 0.75)
o = ca.Opti(); Z, U, T = o.variable(5, N + 1), o.variable(2, N), o.variable(); p = o.parameter(5)
o.subject_to(Z[:, 0] == p)
for i in range(N):
    o.subject_to(Z[:, i + 1] == f(Z[:, i], U[:, i])); o.subject_to(o.bounded(ca.DM([-5, -2.8]), U[:, i], ca.DM([2, 2.8])))
    o.subject_to(cx(Z[:, i]) + 1e-4 * i <= T)
o.subject_to(Z[3, N] == 0); o.subject_to(cx(Z[:, N]) + 1e-4 * N <= 0); o.minimize(T)
o.solver("ipopt", {"print_time": False}, {"print_level": 0, "sb": "yes", "max_iter": 2000, "tol": 1e-9})
fn = ca.Function("f", [xs := ca.SX.sym("x", 5), us := ca.SX.sym("u", 2)], [f(xs, us)])
cf = ca.Function("c", [xs], [cx(xs)])
rng = np.random.default_rng(0)
worse = 0
for i in pick:
    x = X[i]; vals = []
    for j in range(6):
        tau = np.zeros(N); dd = np.full(N, 0.0 if j == 0 else rng.uniform(-2.8, 2.8)); v = x[3]
        for m in range(N):
            tau[m] = np.clip(-v / TS, -5, 2); v += TS * tau[m]
        z = [x]
        for m in range(N):
            z.append(np.array(fn(z[-1], [tau[m], dd[m]])).reshape(-1))
        o.set_value(p, x); o.set_initial(Z, np.array(z).T); o.set_initial(U, np.vstack([tau, dd])); o.set_initial(T, 0.0)
        try:
            s = o.solve(); zz = s.value(Z)
            term = float(np.max(np.array(cf(zz[:, N])).reshape(-1) + 1e-4 * N))
            if term <= 1e-7 and abs(zz[3, N]) <= 1e-7:
                vals.append(max(float(np.max(np.array(cf(zz[:, k])).reshape(-1) + 1e-4 * k)) for k in range(N)))
        except RuntimeError:
            pass
    own = min(vals) if vals else np.nan
    worse += own < cols["h"][i] - 1e-6
    print(f"row {i}: label {cols['h'][i]:+.6f}  own min h̄ {own:+.6f}  ({len(vals)}/6)")
print("labels above the own minimum:", worse, "of", len(pick))
