"""Audit D: rows of the sampled chunk whose label h (2.24) the own solve beat: verify the own
point by a numpy rollout, and solve the project's compiled (2.24) cold and from the own point."""
import pickle
import sys

import casadi as ca
import numpy as np

from balustrade.examples.obstacles import obstacle_problems

cols = pickle.load(open(sys.argv[1], "rb"))
X = np.column_stack([cols[f"x{j}"] for j in range(5)])
rows = [int(a) for a in sys.argv[2:]]
TS, L, N = 0.02, 0.09, 50
obs = np.array([(ox, oy, 0.15) for ox in (-0.8, 0, 0.8) for oy in (-0.8, 0, 0.8)])
def fnp(x, u):
    px, py, psi, v, de = x
    return np.array([px + TS * v * np.cos(psi), py + TS * v * np.sin(psi), psi + TS * v / L * np.tan(de),
                     v + TS * u[0], de + TS * u[1]])
def cxnp(x):
    return np.r_[obs[:, 2] ** 2 - (x[0] - obs[:, 0]) ** 2 - (x[1] - obs[:, 1]) ** 2, x[4] - 0.75, -x[4] - 0.75]
def h_of_inputs(x, U):
    z = [x]
    for i in range(N):
        z.append(fnp(z[-1], U[:, i]))
    z = np.array(z)
    s = sum(max(0.0, float(np.max(cxnp(z[i]) + 1e-4 * i))) for i in range(N))
    term = float(np.max(cxnp(z[N]) + 1e-4 * N))
    return s, term, z[N, 3], z
# own solve (as in d_obstacles_data) with a braking rollout start
def f(x, u):
    return ca.vertcat(x[0] + TS * x[3] * ca.cos(x[2]), x[1] + TS * x[3] * ca.sin(x[2]),
                      x[2] + TS * x[3] / L * ca.tan(x[4]), x[3] + TS * u[0], x[4] + TS * u[1])
def cx(x):
    return ca.vertcat(*[r ** 2 - (x[0] - ox) ** 2 - (x[1] - oy) ** 2 for ox, oy, r in obs], x[4] - 0.75, -x[4] - 0.75)
o = ca.Opti(); Z, U, S = o.variable(5, N + 1), o.variable(2, N), o.variable(1, N); p = o.parameter(5)
o.subject_to(Z[:, 0] == p)
for i in range(N):
    o.subject_to(Z[:, i + 1] == f(Z[:, i], U[:, i]))
    o.subject_to(o.bounded(ca.DM([-5, -2.8]), U[:, i], ca.DM([2, 2.8])))
    o.subject_to(cx(Z[:, i]) + 1e-4 * i <= S[0, i])
o.subject_to(S >= 0); o.subject_to(Z[3, N] == 0); o.subject_to(cx(Z[:, N]) + 1e-4 * N <= 0)
o.minimize(ca.sum2(S))
o.solver("ipopt", {"print_time": False}, {"print_level": 0, "sb": "yes", "max_iter": 2000, "tol": 1e-8})
pb = obstacle_problems("exact")
for i in rows:
    x = X[i]
    n = max(1, int(np.ceil(x[3] / 5 / TS)))
    tau = np.r_[np.full(n, -x[3] / (n * TS)), np.zeros(N - n)]
    z = [x]
    for k in range(N):
        z.append(fnp(z[-1], [tau[k], 0.0]))
    o.set_value(p, x); o.set_initial(Z, np.array(z).T); o.set_initial(U, np.vstack([tau, np.zeros(N)])); o.set_initial(S, 0.1)
    sol = o.solve()
    Uo = sol.value(U)
    s, term, vN, zz = h_of_inputs(x, Uo)
    cold = pb.slack.solve({"x0": x})
    cold2 = pb.slack_cold.solve({"x0": x}) if pb.slack_cold is not None else None
    warm = pb.slack.solve({"x0": x}, warm_start={"x": sol.value(Z), "u": Uo})
    # the project's solver from braking rollouts (a stop in n steps, constant steering rate)
    brk = []
    for rate in (0.0, 1.4, -1.4, 2.8, -2.8):
        zz_ = [x]; uu_ = np.vstack([tau, np.full(N, rate)])
        for k in range(N):
            zz_.append(fnp(zz_[-1], uu_[:, k]))
        sb = pb.slack.solve({"x0": x}, warm_start={"x": np.array(zz_).T, "u": uu_})
        brk.append(round(float(sb.objective), 5) if sb.success else None)
    print(f"row {i} x={np.round(x, 3)} label h={cols['h'][i]:.5f} in_s={cols['in_s'][i]}; own point by rollout: "
          f"h={s:.2e}, terminal row max {term:+.2e}, v_N {vN:+.1e}, min over u bounds ok {np.all(Uo[0]>=-5-1e-9) and np.all(Uo[0]<=2+1e-9) and np.all(np.abs(Uo[1])<=2.8+1e-9)}; "
          f"project cold {cold.status} {float(cold.objective):.5f}; cold twin "
          f"{None if cold2 is None else round(float(cold2.objective), 5)}; from own point {warm.status} {float(warm.objective):.5f}; from braking rollouts {brk}")
if False: print("var names", list(pb.slack.solve({"x0": X[rows[0]]}).primal.keys()) if hasattr(pb.slack.solve({"x0": X[rows[0]]}), "primal") else "?")
