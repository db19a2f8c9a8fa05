"""Audit D: the §8.3 quick closed loops (Algorithm 7.5, committed net), rechecked independently:
own signed distance, own model (8.1) in numpy, own ĥ via the numpy MLP, own check of every
certified step and of the decrease condition of every solved step."""
import os

os.makedirs("/tmp/audit_d", exist_ok=True)  # scratch files of the audit D scripts
import pickle
import time

import numpy as np

import balustrade.reproduce.obstacles as ob
from balustrade.control.approximate import ApproximatePCBFFilter
from balustrade.control.base import simulate as _simulate
from balustrade.learn.export import to_casadi
from balustrade.learn.train import MLPModel
from balustrade.models.obstacle_car import obstacle_car, obstacle_setup

traces = []
def sim(*a, **k):
    tr = _simulate(*a, **k); traces.append(tr); return tr
ob.simulate = sim
model = MLPModel.load(ob.NET)
s = obstacle_setup()
filt = ApproximatePCBFFilter(obstacle_car(), s.U, to_casadi(model), rho=ob.RHO,
                             target=ob.FILTER_TARGET, network=model)
mpc = ob.NaiveMPC()
t = time.time()
runs = ob.closed_loops(filt, mpc)
print("closed loops", time.time() - t, "s")
m = ob.loop_metrics(runs)
pickle.dump({"runs": runs, "traces": [dict(states=tr.states, inputs=tr.inputs, proposed=tr.proposed,
             values={k: np.asarray(v) for k, v in tr.values.items()}, statuses=tr.statuses,
             fallbacks=tr.fallbacks) for tr in traces], "metrics": m},
            open("/tmp/audit_d/obst_runs.pkl", "wb"))
print("project: min signed distance", m["min_signed_distance"], "all_safe", m["all_safe"],
      "paths", m["paths"], "changed", m["steps_input_changed"], "/", m["steps"])

TS, L = 0.02, 0.09
def f_np(x, u):
    px, py, psi, v, de = x
    return np.array([px + TS * v * np.cos(psi), py + TS * v * np.sin(psi),
                     psi + TS * v / L * np.tan(de), v + TS * u[0], de + TS * u[1]])
obs = [(ox, oy, 0.15) for ox in (-0.8, 0, 0.8) for oy in (-0.8, 0, 0.8)]
ulb, uub = np.array([-5.0, -2.8]), np.array([2.0, 2.8])
for r, tr in zip(runs, traces):
    X, U, Up = tr.states, tr.inputs, tr.proposed
    own = min(np.hypot(x[0] - ox, x[1] - oy) - rr for x in X for ox, oy, rr in obs)
    dyn = max(np.max(np.abs(f_np(X[k], U[k]) - X[k + 1])) for k in range(len(U)))
    bad_cert, cert, bad_dec, n_dec, worst_dec = [], 0, [], 0, -np.inf
    hX = model(X)
    for k, (st, p) in enumerate(zip(tr.statuses, r["paths"])):
        if p == "certified":
            cert += 1
            hn = float(model(f_np(X[k], Up[k])[None])[0])
            ok = np.array_equal(U[k], Up[k]) and np.all(Up[k] >= ulb) and np.all(Up[k] <= uub) and hn <= 0
            if not ok:
                bad_cert.append((k, hn, U[k] - Up[k]))
        elif p in ("both_solves", "decrease_solved_proposal_kept"):
            n_dec += 1
            dh = tr.values["dh"][k]
            # own Δĥ lower bound on a dense input grid (true max decrease >= this)
            g = np.stack(np.meshgrid(np.linspace(-5, 2, 71), np.linspace(-2.8, 2.8, 57)), -1).reshape(-1, 2)
            nxt = np.array([f_np(X[k], u) for u in g])
            dh_grid = hX[k] - model(nxt).min()
            lhs = float(model(f_np(X[k], U[k])[None])[0] - hX[k])
            viol = lhs + ob.RHO * dh
            worst_dec = max(worst_dec, viol)
            if viol > 1e-6 or dh_grid > dh + 1e-6 * max(1, abs(dh)) or np.any(U[k] < ulb - 1e-7) or np.any(U[k] > uub + 1e-7):
                bad_dec.append((k, p, float(viol), float(dh), float(dh_grid)))
    print(f"start {r['start']}: min dist project {r['min_distance']:.6f} own {own:.6f}; dyn err {dyn:.1e}; "
          f"certified {cert} bad {bad_cert[:3]}; solved {n_dec} worst decrease viol {worst_dec:.2e} "
          f"bad {bad_dec[:4]}; max|δ| {np.abs(X[:,4]).max():.4f}; ĥ>0 states {int(np.sum(hX>0))}")
