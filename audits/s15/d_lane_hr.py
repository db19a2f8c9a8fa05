"""Audit D: h_r of (5.15) recomputed independently (own casadi Opti formulation, multi-start)
at states of a robust (Algorithm 5.2) closed loop from X0, seed 0, and monotonicity of h_r."""
import pickle
import sys
import time

import casadi as ca
import numpy as np

from balustrade.models.bicycle import TS, WHEELBASE
from balustrade.reproduce import lane_change as lc

DEG = np.pi / 180
STEPS = int(sys.argv[1]) if len(sys.argv) > 1 else 40
d = lc.design(lc.config("converging"))
ctrl = lc.controllers(d, rho=0.5)["robust"]
ws = lc.disturbances(d, 0, lc.STEPS)[:STEPS]
t0 = time.time()
import os

os.makedirs("/tmp/audit_d", exist_ok=True)
r = lc.closed_loop(ctrl, d, ws)   # no cache: a pickle of older code would be reused silently
print("closed loop", time.time() - t0, "s; statuses", set(r["statuses"]), "fallbacks", set(r["fallbacks"]))
h = r["h_r"]
print("h_r", np.array2string(h[:20], precision=4))
print("max increase", np.max(np.diff(h[np.isfinite(h)])))
pickle.dump(r, open("/tmp/audit_d/lane_robust_seed0.pkl", "wb"))

P, K = d.error.E.P, d.error.K
Ep = np.linalg.inv(P)
N, deltas, alpha = d.N, d.deltas, d.alpha_f
Xlb = np.array([-0.2, -35 * DEG, 0.5, -35 * DEG]); Xub = np.array([0.2, 35 * DEG, 1.3, 35 * DEG])
Ulb = np.array([-17.5 * DEG, -2.0]); Uub = -Ulb
sx = np.sqrt(np.diag(Ep)); su = np.sqrt(np.diag(K @ Ep @ K.T))
xlb, xub, vlb, vub = Xlb + sx, Xub - sx, Ulb + su, Uub - su
Pf, xs = d.cbf.P, d.cbf.x_s

def f_ca(x, u):
    return ca.vertcat(x[0] + TS * x[2] * ca.sin(x[1]), x[1] + TS * x[2] / WHEELBASE * ca.tan(x[3]),
                      x[2] + TS * u[1], x[3] + u[0])
opti = ca.Opti()
Z, V = opti.variable(4, N + 1), opti.variable(2, N)
XI, XIN = opti.variable(8, N), opti.variable()
x0 = opti.parameter(4)
opti.subject_to(ca.mtimes([(x0 - Z[:, 0]).T, ca.DM(P), x0 - Z[:, 0]]) <= 1)
for i in range(N):
    opti.subject_to(Z[:, i + 1] == f_ca(Z[:, i], V[:, i]))
    opti.subject_to(opti.bounded(vlb, V[:, i], vub))
    opti.subject_to(Z[:, i] - xub + deltas[i] <= XI[:4, i])
    opti.subject_to(xlb - Z[:, i] + deltas[i] <= XI[4:, i])
opti.subject_to(ca.vec(XI) >= 0); opti.subject_to(XIN >= 0)
dN = Z[:, N] - xs
opti.subject_to(ca.mtimes([dN.T, ca.DM(Pf), dN]) - 1 <= XIN)
opti.minimize(alpha * XIN + ca.sum1(ca.vec(XI)))
opti.solver("ipopt", {"print_time": False}, {"print_level": 0, "sb": "yes", "tol": 1e-9,
                                            "max_iter": 3000, "bound_relax_factor": 0.0})

def solve(x, guess):
    opti.set_value(x0, x)
    zg, vg = guess
    opti.set_initial(Z, zg); opti.set_initial(V, vg)
    opti.set_initial(XI, 0.1); opti.set_initial(XIN, 0.0)
    try:
        s = opti.solve()
        z = s.value(Z)
        # polished slacks of the point (exact, as h_r is defined): max(0, rows), max(0, h_f)
        rows = np.r_[z[:, :N] - xub[:, None], xlb[:, None] - z[:, :N]] + deltas[None, :]
        hfN = (z[:, N] - xs) @ Pf @ (z[:, N] - xs) - 1
        tube = (x - z[:, 0]) @ P @ (x - z[:, 0]) - 1
        assert tube <= 1e-7, tube
        return float(np.maximum(rows, 0).sum() + alpha * max(hfN, 0.0)), z, s.value(V)
    except RuntimeError:
        return np.nan, None, None

def rollout(x, pol):
    z = np.zeros((4, N + 1)); v = np.zeros((2, N)); z[:, 0] = x
    for i in range(N):
        v[:, i] = np.clip(pol(z[:, i]), vlb, vub)
        z[:, i + 1] = np.array(f_ca(z[:, i], v[:, i])).reshape(-1)
    return z, v

Kf = d.cbf.K
rng = np.random.default_rng(0)
for k in [0, 1, 2, 3, 5, 8, 10, 15, 20, 30, 39]:
    if k >= STEPS:
        continue
    x = r["states"][k]
    guesses = [rollout(x, lambda z: Kf @ (z - xs)), rollout(x, lambda z: np.zeros(2))]
    for _ in range(3):
        gain = rng.uniform(0.2, 1.5)
        guesses.append(rollout(x, lambda z, g=gain: g * (Kf @ (z - xs))))
    vals = [solve(x, g)[0] for g in guesses]
    best = np.nanmin(vals)
    print(f"k={k:3d} project h_r={h[k]:.6e}  own min={best:.6e}  (starts {np.round(vals, 6)})  "
          f"diff={h[k]-best:+.2e}")
