"""Audit E: PCBFSafetyFilter.build's defaults (target "fast-sqp", slack_norm 1, eps 1e-6) on the
shipped pendulum example (Section 7.5) vs the same filter on target "cvxpy" (the convex
pendulum problems transcribed by cvxpy: an independent backend). Cold steps (reset each) at
random states in and beyond X and random proposals; compare h_PB and the input."""
import numpy as np

from balustrade.control import PCBFSafetyFilter
from balustrade.examples.pendulum import pendulum_terminal_cbf
from balustrade.models.pendulum import pendulum, pendulum_setup

system, s = pendulum(), pendulum_setup()
h_f = pendulum_terminal_cbf()
default = PCBFSafetyFilter.build(system, s.X, s.U, h_f, s.N, s.deltas, alpha_f=s.alpha_f)
ref = PCBFSafetyFilter.build(system, s.X, s.U, h_f, s.N, s.deltas, alpha_f=s.alpha_f, target="cvxpy")
rng = np.random.default_rng(3)
worst_h = worst_u = 0.0
rows = []
for i in range(120):
    x = rng.uniform(-1.3, 1.3, 2) * np.array([0.5, 1.5])
    u_p = rng.uniform(-5, 5, 1)
    default.reset(); ref.reset()
    ua, ia = default.step(x, u_p)
    ub, ib = ref.step(x, u_p)
    ha, hb = ia.values.get("h_PB", np.nan), ib.values.get("h_PB", np.nan)
    dh = abs(ha - hb) / (1 + abs(hb)); du = float(np.max(np.abs(ua - ub)))
    if not (np.isfinite(dh) and dh < 1e-5 and du < 1e-4) or ia.status != ib.status:
        rows.append((i, np.round(x, 4), u_p, ia.status, ib.status, ha, hb, ua, ub, ia.fallback, ib.fallback))
    else:
        worst_h, worst_u = max(worst_h, dh), max(worst_u, du)
print(f"agreeing steps: worst rel h_PB gap {worst_h:.1e}, worst |du| {worst_u:.1e}; {len(rows)} differ")
for r in rows[:20]: print(r)
