"""(copy of e_daqp_scale.py with the direct backend's Clarabel, fast-convex-conic, in place of DAQP and PIQP) Audit E: the DAQP engine (fast-convex-daqp) on scale-trick QPs vs PIQP (fast-convex-qp)
and cvxpy+Clarabel ("conic"): rows scaled by s = 1e-9 .. 1e9 (A(p) = s*a, b = s*beta), zero
rows (s = 0 with beta >= 0 and beta < 0), equality rows scaled, a degenerate LP direction.
Each instance solved in a shuffled sequence by one hot engine."""
import numpy as np

from balustrade.backends import compile
from balustrade.backends.solution import Status
from balustrade.dsl import OCP, squared_norm


def make():
    ocp = OCP(name="scaled_qp")
    y = ocp.variable("y", 4)
    c = ocp.parameter("c", 4)
    s = ocp.parameter("s", 3)          # row scales
    bb = ocp.parameter("bb", 3)
    ocp.le(s[0] * (y[0] + y[1]), bb[0], name="r0")
    ocp.le(s[1] * (y[1] - y[2]), bb[1], name="r1")
    ocp.eq(s[2] * (y[0] + y[3]), bb[2], name="e0")
    ocp.le(y, 3.0, name="up"); ocp.le(-y, 3.0, name="lo")
    # cost on y0..y2 only: y3 is fixed only through the equality (semidefinite P)
    ocp.minimize(squared_norm(y[:3] - c[:3]) + c[3] * y[3])
    return ocp

ocp = make()
dq, pq, cl = compile(ocp, "fast-convex-conic"), compile(ocp, "fast-convex-conic"), compile(ocp, "conic")
rng = np.random.default_rng(0)
insts = []
for k in range(300):
    sc = 10.0 ** rng.choice([-9, -6, -3, 0, 3, 6, 9], size=3)
    if rng.random() < 0.1: sc[rng.integers(3)] = 0.0
    beta = rng.uniform(-1, 1, 3)
    insts.append({"c": rng.uniform(-4, 4, 4), "s": sc, "bb": sc * beta if rng.random() < 0.8 else rng.uniform(-1, 1, 3)})
worst = {}
issues = []
for k, p in enumerate(insts):
    a, b, c = dq.solve(p), pq.solve(p), cl.solve(p)
    if a.status != b.status:
        issues.append((k, "status daqp-engine vs piqp", str(a.status), str(b.status), str(c.status), p["s"], a.message[:160]))
        continue
    if a.status == Status.OPTIMAL:
        ref = c.objective if c.status == Status.OPTIMAL else b.objective
        d = abs(a.objective - ref) / (1 + abs(ref))
        if d > 1e-6:
            issues.append((k, "objective", a.objective, b.objective, c.objective, str(c.status), p["s"], a.solver, a.message[:160]))
        worst[a.solver] = max(worst.get(a.solver, 0), d)
    elif c.status == Status.OPTIMAL:
        issues.append((k, "engine says", str(a.status), "clarabel optimal", c.objective, p["s"], a.message[:200]))
print("worst rel objective gap by answering solver:", worst)

for i in issues[:30]: print(i)
print(len(issues), "issues")
