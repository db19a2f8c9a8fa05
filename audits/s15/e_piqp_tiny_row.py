"""Audit E: a row scaled by 1e-9 (1e-9·(y0 + y3) = 1e-9·β) is ignored by the direct backend's
PIQP answer, reported optimal, while Clarabel (cvxpy) and DAQP (KKT-checked) keep it.
Distance of the answers from the equality y0 + y3 = β printed."""
from balustrade.backends import compile
from balustrade.dsl import OCP, squared_norm

ocp = OCP(name="tiny_eq")
y = ocp.variable("y", 2)
s = ocp.parameter("s", 1)
ocp.eq(s[0] * (y[0] + y[1]), s[0] * 1.0, name="e0")
ocp.le(y, 3.0, name="up"); ocp.le(-y, 3.0, name="lo")
ocp.minimize(squared_norm(y[0] - 2.0) + y[1])
for tgt in ("fast-convex-qp", "fast-convex", "fast-convex-daqp", "conic", "fast-convex-sized"):
    c = compile(ocp, tgt)
    for sc in (1.0, 1e-6, 1e-9):
        sol = c.solve({"s": [sc]})
        w = sol.primal["y"].ravel() if sol.primal.get("y") is not None else None
        print(f"{tgt:18s} s={sc:7.0e} {str(sol.status):10s} obj={sol.objective: .6f} y={w} |y0+y1-1|={abs(w.sum()-1) if w is not None else None:.2e} solver={sol.solver}")
