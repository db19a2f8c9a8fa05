"""Audit E: the DAQP engine on (4.5) at the edge of feasibility: for random directions d and
Θ's, t* = sup{t : (4.5) feasible at x0 = t·d} bisected with PIQP to 1e-11, then the hot DAQP
engine at t*(1 - 1e-9) (feasible, degenerate: many active rows), t*(1 + 1e-9), and t*.
Statuses vs PIQP and Clarabel ("conic"); DAQP-accepted objectives vs Clarabel."""
import sys

import numpy as np

from balustrade.backends import compile
from balustrade.backends.solution import Status
from balustrade.dsl.sets import Box
from balustrade.reproduce import msd_adaptive

count = int(sys.argv[1]) if len(sys.argv) > 1 else 20
rng = np.random.default_rng(int(sys.argv[2]) if len(sys.argv) > 2 else 0)
d = msd_adaptive.design(3)
ctrl = msd_adaptive.adaptive_controller(d, target="fast-convex-daqp")
ocp = ctrl._problem(ctrl.N, n_vertices=4)
lo, hi = ctrl.Theta0.lb, ctrl.Theta0.ub
dq, pq, cl = compile(ocp, "fast-convex-daqp"), compile(ocp, "fast-convex-qp"), compile(ocp, "conic")
out = {"daqp_opt": 0, "fallback_opt": 0, "infeasible_agree": 0, "mismatch": [], "worst_obj": 0.0}
for i in range(count):
    kind = i % 3
    if kind == 0: T = ctrl.Theta0
    elif kind == 1:
        p = rng.uniform(lo, hi); T = Box(p, p, name="pt")
    else:
        a, b = rng.uniform(lo, hi), rng.uniform(lo, hi); T = Box(np.minimum(a, b), np.maximum(a, b), name="sub")
    ctrl._set_theta(T)
    idx = np.arange(4) % len(ctrl.vertices)
    th, s = ctrl.vertices[idx].T.copy(), ctrl._s[:, idx].copy()
    direction = rng.normal(size=6); u = rng.uniform(-6, 6, 3)
    par = lambda t: {"x0": t * direction, "u_p": u, "theta": th, "s": s}
    a_, b_ = 0.0, 10.0
    if pq.solve(par(b_)).status == Status.OPTIMAL: continue
    for _ in range(60):
        m = 0.5 * (a_ + b_)
        (a_, b_) = (m, b_) if pq.solve(par(m)).status == Status.OPTIMAL else (a_, m)
    for t in (a_ * (1 - 1e-9), a_, b_, b_ * (1 + 1e-9)):
        x, y, z = dq.solve(par(t)), pq.solve(par(t)), cl.solve(par(t))
        if x.status != y.status:
            out["mismatch"].append((i, t, str(x.status), str(y.status), str(z.status), x.message[:150]))
        elif x.status == Status.OPTIMAL:
            out["daqp_opt" if x.solver == "daqp" else "fallback_opt"] += 1
            if z.status == Status.OPTIMAL:
                out["worst_obj"] = max(out["worst_obj"], abs(x.objective - z.objective) / (1 + abs(z.objective)))
        elif x.status == Status.INFEASIBLE:
            out["infeasible_agree"] += 1
            if z.status == Status.OPTIMAL:
                out["mismatch"].append((i, t, "both infeasible but clarabel optimal", z.objective))
print({k: v for k, v in out.items() if k != "mismatch"})
for m in out["mismatch"]: print(m)
print("engine verified", dq.engine.verified, "fallbacks", dq.engine.fallbacks)
