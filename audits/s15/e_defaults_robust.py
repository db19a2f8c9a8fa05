"""Audit E: Algorithm 5.2 (RobustPCBFSafetyFilter.build) and the nominal PCBF of ch5_robust on
their default targets vs the same design on target "cvxpy", cold steps at random states.
Also states near the boundary. Compares h_r / h_PB and the input."""
import warnings

import numpy as np

from balustrade.reproduce import ch5_robust

warnings.simplefilter("ignore")
N = 30
import sys

SC = float(sys.argv[1]) if len(sys.argv) > 1 else 0.9
dflt = ch5_robust.build(N)
ref = ch5_robust.build(N, "cvxpy")
rng = np.random.default_rng(5)
for name, key in (("robust", "h_r"), ("nominal", "h_PB")):
    a, b = dflt[name], ref[name]
    worst_h = worst_u = 0.0; rows = []
    for i in range(60):
        x = rng.uniform(-SC, SC, 2) * np.array([1.0, 10.0])
        u_p = rng.uniform(-6, 6, 1)
        a.reset(); b.reset()
        ua, ia = a.step(x, u_p); ub, ib = b.step(x, u_p)
        ha, hb = ia.values.get(key, np.nan), ib.values.get(key, np.nan)
        dh = abs(ha - hb) / (1 + abs(hb)); du = float(np.max(np.abs(ua - ub)))
        if not (np.isfinite(dh) and dh < 1e-5 and du < 1e-4) or ia.status != ib.status:
            rows.append((i, np.round(x, 3), np.round(u_p, 3), ia.status, ib.status, ha, hb, ua, ub))
        else:
            worst_h, worst_u = max(worst_h, dh), max(worst_u, du)
    print(f"{name}: default solvers {a.slack.__class__.__name__}; agreeing: worst rel {key} gap {worst_h:.1e}, |du| {worst_u:.1e}; {len(rows)} differ")
    for r in rows[:10]: print("  ", r)
