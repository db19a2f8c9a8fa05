"""Audit D: recheck the decrease condition of (7.5) (with the project's extended bound
max(-ρΔĥ, -Δĥ)) and Δĥ against an own dense input grid, from the pickled quick loops."""
import pickle

import numpy as np

import balustrade.reproduce.obstacles as ob
from balustrade.learn.train import MLPModel

D = pickle.load(open("/tmp/audit_d/obst_runs.pkl", "rb"))
model = MLPModel.load(ob.NET)
TS, L = 0.02, 0.09
def f_many(x, U):
    px, py, psi, v, de = x
    return np.column_stack([np.full(len(U), px + TS * v * np.cos(psi)), np.full(len(U), py + TS * v * np.sin(psi)),
                            np.full(len(U), psi + TS * v / L * np.tan(de)), v + TS * U[:, 0], de + TS * U[:, 1]])
g = np.stack(np.meshgrid(np.linspace(-5, 2, 141), np.linspace(-2.8, 2.8, 113)), -1).reshape(-1, 2)
from collections import Counter

for r, tr in zip(D["runs"], D["traces"]):
    X, U, Up = tr["states"], tr["inputs"], tr["proposed"]
    hX = model(X)
    worst, worst_dh, st = -np.inf, -np.inf, Counter()
    for k, p in enumerate(r["paths"]):
        if p not in ("both_solves", "decrease_solved_proposal_kept"):
            continue
        st[tr["statuses"][k]] += 1
        dh = tr["values"]["dh"][k]
        hn = model(f_many(X[k], g))
        dh_grid = hX[k] - hn.min()
        lhs = float(model(f_many(X[k], U[k][None]))[0] - hX[k])
        viol = lhs - max(-ob.RHO * dh, -dh) - 1e-6
        worst = max(worst, viol)
        worst_dh = max(worst_dh, dh_grid - dh)
        if dh_grid - dh > 1e-4 * max(1, abs(dh)):
            print(f"  {r['start']} k={k}: (7.6) local: recorded Δĥ={dh:.5f} grid Δĥ={dh_grid:.5f}")
    print(f"{r['start']}: worst (7.5) violation {worst:.2e}; worst grid-minus-recorded Δĥ {worst_dh:.2e}; statuses {dict(st)}")
