"""Audit D: h_PB of (2.24) recorded by the quick reproduction's PCBF timing (3 states of the
first run where the filter intervened), recomputed with an own multi-start Opti solve."""
import pickle

import casadi as ca
import numpy as np

D = pickle.load(open("/tmp/audit_d/obst_runs.pkl", "rb"))
r = D["runs"][0]
idx = np.nonzero(r["changed"])[0]
idx = idx[np.linspace(0, len(idx) - 1, 3).round().astype(int)]
TS, L, N = 0.02, 0.09, 50
obs = [(ox, oy, 0.15) for ox in (-0.8, 0, 0.8) for oy in (-0.8, 0, 0.8)]
def f(x, u):
    return ca.vertcat(x[0] + TS * x[3] * ca.cos(x[2]), x[1] + TS * x[3] * ca.sin(x[2]),
                      x[2] + TS * x[3] / L * ca.tan(x[4]), x[3] + TS * u[0], x[4] + TS * u[1])
def cx(x):
    return ca.vertcat(*[q ** 2 - (x[0] - ox) ** 2 - (x[1] - oy) ** 2 for ox, oy, q in obs], x[4] - 0.75, -x[4] - 0.75)
o = ca.Opti(); Z, U, S = o.variable(5, N + 1), o.variable(2, N), o.variable(1, N); p = o.parameter(5)
o.subject_to(Z[:, 0] == p)
for i in range(N):
    o.subject_to(Z[:, i + 1] == f(Z[:, i], U[:, i]))
    o.subject_to(o.bounded(ca.DM([-5, -2.8]), U[:, i], ca.DM([2, 2.8])))
    o.subject_to(cx(Z[:, i]) + 1e-4 * i <= S[0, i])
o.subject_to(S >= 0); o.subject_to(Z[3, N] == 0); o.subject_to(cx(Z[:, N]) + 1e-4 * N <= 0)
o.minimize(ca.sum2(S))
o.solver("ipopt", {"print_time": False}, {"print_level": 0, "sb": "yes", "max_iter": 2000, "tol": 1e-9, "bound_relax_factor": 0.0})
fn = ca.Function("f", [xs := ca.SX.sym("x", 5), us := ca.SX.sym("u", 2)], [f(xs, us)])
cf = ca.Function("c", [xs], [cx(xs)])
rng = np.random.default_rng(0)
for k in idx:
    x = r["states"][k]; vals = []
    for j in range(8):
        tau = np.zeros(N); dd = np.full(N, 0.0 if j == 0 else rng.uniform(-2.8, 2.8)); v = x[3]
        for m in range(N):
            tau[m] = np.clip(-v / TS, -5, 2); v += TS * tau[m]
        z = [x]
        for m in range(N):
            z.append(np.array(fn(z[-1], [tau[m], dd[m]])).reshape(-1))
        o.set_value(p, x); o.set_initial(Z, np.array(z).T); o.set_initial(U, np.vstack([tau, dd])); o.set_initial(S, 0.05)
        try:
            s = o.solve(); zz = s.value(Z)
            vals.append(sum(max(0.0, float(np.max(np.array(cf(zz[:, i])).reshape(-1) + 1e-4 * i))) for i in range(N)))
        except RuntimeError:
            pass
    print(f"step {k}: own min h_PB = {min(vals) if vals else np.nan:.6e} over {len(vals)}/8 converged starts")
