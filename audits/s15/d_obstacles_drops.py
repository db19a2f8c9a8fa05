"""Audit D: states the §8.3 sampler drops ((2.24) failed): are they infeasible? Random states of
the sampling domain near the discs, the project's Evaluator (cold), then for dropped ones an own
multi-start feasibility search (casadi Opti, hard terminal v_N = 0, rows + Δ_N <= 0)."""
import sys
import time

import casadi as ca
import numpy as np

from balustrade.examples.obstacles import obstacle_problems
from balustrade.learn.sampler import Evaluator, Seed

rng = np.random.default_rng(int(sys.argv[1]) if len(sys.argv) > 1 else 0)
n = int(sys.argv[2]) if len(sys.argv) > 2 else 40
TS, L, N = 0.02, 0.09, 50
obs = [(ox, oy, 0.15) for ox in (-0.8, 0, 0.8) for oy in (-0.8, 0, 0.8)]
# states near a disc (within 0.4 m of a centre), any heading, speeds 0-4
c = np.array(obs)[rng.integers(9, size=n), :2]
ang, rad = rng.uniform(0, 2 * np.pi, n), rng.uniform(0.0, 0.4, n)
X = np.column_stack([c[:, 0] + rad * np.cos(ang), c[:, 1] + rad * np.sin(ang),
                     rng.uniform(-np.pi, np.pi, n), rng.uniform(0, 4, n), rng.uniform(-0.75, 0.75, n)])
ev = Evaluator(obstacle_problems())
t = time.time()
S = [ev.point(x, Seed(x))[0] for x in X]
bad = [i for i, s in enumerate(S) if not s.ok]
print(f"{n} states, {len(bad)} dropped, {time.time() - t:.0f} s; reasons {set(S[i].reason for i in bad)}")
def f(x, u):
    return ca.vertcat(x[0] + TS * x[3] * ca.cos(x[2]), x[1] + TS * x[3] * ca.sin(x[2]),
                      x[2] + TS * x[3] / L * ca.tan(x[4]), x[3] + TS * u[0], x[4] + TS * u[1])
def cx(x):
    return ca.vertcat(*[r ** 2 - (x[0] - ox) ** 2 - (x[1] - oy) ** 2 for ox, oy, r in obs], x[4] - 0.75, -x[4] - 0.75)
o = ca.Opti(); Z, U = o.variable(5, N + 1), o.variable(2, N); p = o.parameter(5)
o.subject_to(Z[:, 0] == p)
for i in range(N):
    o.subject_to(Z[:, i + 1] == f(Z[:, i], U[:, i]))
    o.subject_to(o.bounded(ca.DM([-5, -2.8]), U[:, i], ca.DM([2, 2.8])))
o.subject_to(Z[3, N] == 0); o.subject_to(cx(Z[:, N]) + 1e-4 * N <= 0)
o.minimize(1e-6 * ca.sumsqr(U))
o.solver("ipopt", {"print_time": False}, {"print_level": 0, "sb": "yes", "max_iter": 1000})
fnp = ca.Function("f", [xs := ca.SX.sym("x", 5), us := ca.SX.sym("u", 2)], [f(xs, us)])
for i in bad:
    x = X[i]; found = 0
    for j in range(8):
        tau = np.zeros(N); k = rng.integers(1, N); acc = rng.uniform(-2, 2)
        v = x[3]
        for m in range(N):
            tau[m] = np.clip(acc if m < k else -v / TS, -5, 2); v += TS * tau[m]
        dd = np.full(N, rng.uniform(-2.8, 2.8))
        z = [x]
        for m in range(N):
            z.append(np.array(fnp(z[-1], [tau[m], dd[m]])).reshape(-1))
        o.set_value(p, x); o.set_initial(Z, np.array(z).T); o.set_initial(U, np.vstack([tau, dd]))
        try:
            o.solve(); found += 1
        except RuntimeError:
            pass
    dmin = min(np.hypot(x[0] - a, x[1] - b) - r for a, b, r in obs)
    print(f"dropped {np.round(x, 3)} (signed dist {dmin:+.3f}, reason {S[i].reason!r}): own feasible {found}/8")
