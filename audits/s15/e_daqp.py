"""Audit E: the hot DAQP engine (fast-convex-daqp) on (4.5) of the 3-mass design vs PIQP and
vs cvxpy+Clarabel (target "conic": the cvxpy transcription, not the direct lowering), on random
states and Θ's: sub-boxes, Θ shrunk to a point, states near/outside the feasible set, u_p far
outside U, exact repeats. One hot engine sees the whole shuffled sequence.
Run: PYTHONPATH=$PWD python audits/s15/e_daqp.py [count] [seed]"""
import sys
import time

import numpy as np

from balustrade.backends import compile
from balustrade.backends.solution import Status
from balustrade.dsl.sets import Box
from balustrade.reproduce import msd_adaptive

count = int(sys.argv[1]) if len(sys.argv) > 1 else 200
seed = int(sys.argv[2]) if len(sys.argv) > 2 else 0
rng = np.random.default_rng(seed)
d = msd_adaptive.design(3)
ctrl = msd_adaptive.adaptive_controller(d, target="fast-convex-daqp")
ocp = ctrl._problem(ctrl.N, n_vertices=4)
lo, hi = ctrl.Theta0.lb, ctrl.Theta0.ub
X0 = d["X0"]

def theta_params(kind):
    if kind == "full":
        T = ctrl.Theta0
    elif kind == "point":
        p = rng.uniform(lo, hi); T = Box(p, p, name="pt")
    elif kind == "thin":
        p = rng.uniform(lo, hi); q = p.copy(); q[0] = min(hi[0], p[0] + 1e-9); T = Box(p, q, name="thin")
    else:
        a, b = rng.uniform(lo, hi), rng.uniform(lo, hi); T = Box(np.minimum(a, b), np.maximum(a, b), name="sub")
    ctrl._set_theta(T)
    idx = np.arange(4) % len(ctrl.vertices)
    return ctrl.vertices[idx].T.copy(), ctrl._s[:, idx].copy()

# states: scaled vertices of X0 (scale ~1 = boundary), random interior, far outside
V = X0.vertices() if hasattr(X0, "vertices") else None
insts = []
for i in range(count):
    kind = rng.choice(["full", "point", "thin", "sub"])
    th, s = theta_params(kind)
    r = rng.random()
    if r < 0.4:
        x = V[rng.integers(len(V))] * rng.uniform(0.95, 1.6)
    elif r < 0.8:
        w = rng.dirichlet(np.ones(len(V))); x = (w @ V) * rng.uniform(0.5, 1.5)
    else:
        x = rng.uniform(-2.5, 2.5, 6)
    u = rng.uniform(-6, 6, 3) if rng.random() < 0.7 else np.zeros(3)
    insts.append(({"x0": x, "u_p": u, "theta": th, "s": s}, kind))
insts += insts[:10]  # exact repeats

dq = compile(ocp, "fast-convex-daqp")
pq = compile(ocp, "fast-convex-qp")
cl = compile(ocp, "conic")
stats = {"n": 0, "opt": 0, "status_mismatch": [], "worst_obj_piqp": 0.0, "worst_obj_clar": 0.0,
         "worst_v_piqp": 0.0, "worst_relobj_clar": 0.0, "daqp_answered": 0, "fallback_answered": 0}
t0 = time.process_time()
for k, (p, kind) in enumerate(insts):
    a, b, c = dq.solve(p), pq.solve(p), cl.solve(p)
    stats["n"] += 1
    if a.status != b.status or (a.status == Status.OPTIMAL) != (c.status == Status.OPTIMAL):
        stats["status_mismatch"].append((k, kind, str(a.status), str(b.status), str(c.status), a.message[:120]))
        continue
    if a.status == Status.OPTIMAL:
        stats["opt"] += 1
        if a.solver == "daqp": stats["daqp_answered"] += 1
        else: stats["fallback_answered"] += 1
        stats["worst_obj_piqp"] = max(stats["worst_obj_piqp"], abs(a.objective - b.objective))
        stats["worst_v_piqp"] = max(stats["worst_v_piqp"], float(np.max(np.abs(a.primal["v"][:, 0] - b.primal["v"][:, 0]))))
        stats["worst_obj_clar"] = max(stats["worst_obj_clar"], abs(a.objective - c.objective))
        stats["worst_relobj_clar"] = max(stats["worst_relobj_clar"], (a.objective - c.objective) / (1 + abs(c.objective)))
        if a.objective - c.objective > 1e-5 * (1 + abs(c.objective)) or c.objective - a.objective > 1e-5 * (1 + abs(c.objective)):
            print("OBJ GAP", k, kind, a.objective, c.objective, b.objective, a.message[:100])
print(stats)
print("engine verified", dq.engine.verified, "fallbacks", dq.engine.fallbacks, "cpu", time.process_time() - t0)
