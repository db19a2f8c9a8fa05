"""Audit D: dropped states of a short-horizon (N = 10, 0.2 s) obstacle walk: a state with
v0 - 5 N T_s > 0 (or v0 + 2 N T_s < 0) cannot reach v_N = 0 (proof by the input bound); any
other dropped state gets an own multi-start feasibility search."""
import sys

import casadi as ca
import numpy as np

from balustrade.learn.sampler import Chunk, ProblemSpec, run_chunk

N, TS, L = 10, 0.02, 0.09
rng = np.random.default_rng(int(sys.argv[1]) if len(sys.argv) > 1 else 4)
lb = np.array([-2, -1.5, -np.pi - 0.5, 0, -0.75]); ub = -lb; ub[3] = 4
chunk = Chunk(0, "geometric", rng.uniform(lb, ub, (8, 5)), seed=5, step=0.1, x_seed=(-0.4, -0.4, 0.0, 0.5, 0.0))
cols = run_chunk(ProblemSpec.of("obstacles", target="exact", N=N), chunk)
X = np.column_stack([cols[f"x{j}"] for j in range(5)])
bad = np.flatnonzero(~cols["ok"])
print(len(X), "rows,", len(bad), "dropped; reasons", set(cols["reason"][bad]))
proven = [i for i in bad if X[i, 3] - 5 * N * TS > 1e-9 or X[i, 3] + 2 * N * TS < -1e-9]
print("infeasible by the speed bound:", len(proven))
obs = [(ox, oy, 0.15) for ox in (-0.8, 0, 0.8) for oy in (-0.8, 0, 0.8)]
def f(x, u):
    return ca.vertcat(x[0] + TS * x[3] * ca.cos(x[2]), x[1] + TS * x[3] * ca.sin(x[2]),
                      x[2] + TS * x[3] / L * ca.tan(x[4]), x[3] + TS * u[0], x[4] + TS * u[1])
def cx(x):
    return ca.vertcat(*[q ** 2 - (x[0] - ox) ** 2 - (x[1] - oy) ** 2 for ox, oy, q in obs], x[4] - 0.75, -x[4] - 0.75)
o = ca.Opti(); Z, U = o.variable(5, N + 1), o.variable(2, N); p = o.parameter(5)
o.subject_to(Z[:, 0] == p)
for i in range(N):
    o.subject_to(Z[:, i + 1] == f(Z[:, i], U[:, i])); o.subject_to(o.bounded(ca.DM([-5, -2.8]), U[:, i], ca.DM([2, 2.8])))
o.subject_to(Z[3, N] == 0); o.subject_to(cx(Z[:, N]) + 1e-4 * N <= 0); o.minimize(1e-6 * ca.sumsqr(U))
o.solver("ipopt", {"print_time": False}, {"print_level": 0, "sb": "yes", "max_iter": 1000})
for i in sorted(set(bad) - set(proven)):
    found = 0
    for j in range(6):
        o.set_value(p, X[i]); o.set_initial(Z, np.tile(X[i][:, None], N + 1)); o.set_initial(U, rng.uniform([-5, -2.8], [2, 2.8], (N, 2)).T)
        try:
            o.solve(); found += 1
        except RuntimeError:
            pass
    print(f"dropped {np.round(X[i], 3)} not proven infeasible by speed; own feasible starts {found}/6")
