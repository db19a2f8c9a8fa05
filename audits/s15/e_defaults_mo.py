"""Audit E: Algorithm 6.4 (MultiobjectivePCBFController.build) on its defaults (target "auto")
vs target "cvxpy", on the §5.6 2-D example (N = 10): closed loops of 15 steps from random
states, same disturbances; compare inputs, h_tilde and statuses step by step."""
import warnings

import numpy as np

from balustrade.control.multiobjective import MultiobjectivePCBFController
from balustrade.design.rpi import ellipsoidal_rpi
from balustrade.design.terminal_cbf import terminal_cbf_with_domain
from balustrade.models.unstable2d import unstable2d, unstable2d_setup

warnings.simplefilter("ignore")
N = 10
system, s = unstable2d(), unstable2d_setup(N)
error = ellipsoidal_rpi(system.A, system.B, s.W, s.X, s.U)
X_E, U_E = error.tighten_state(s.X), error.tighten_input(s.U)
cbf = terminal_cbf_with_domain(system.A, system.B, X_E, U_E, s.deltas()[-1], level=1.0)
args = (system, s.X, s.U, cbf, cbf.policy, N, s.deltas(), error, s.alpha_f)
a = MultiobjectivePCBFController.build(*args)
b = MultiobjectivePCBFController.build(*args, target="cvxpy")
print("default solvers:", type(a.slack).__name__, getattr(a.slack, "solver_name", None), type(a.filter).__name__ if hasattr(a, "filter") else None)
rng = np.random.default_rng(2)
worst_u = worst_h = 0.0; diffs = []
for r in range(20):
    x = rng.uniform([-1.0, -1.4], [1.0, 1.4]); xb = x.copy()
    a.reset(); b.reset()
    for k in range(15):
        u_p = rng.uniform(-2.5, 2.5, 1)
        ua, ia = a.step(x, u_p); ub, ib = b.step(xb, u_p)
        ha, hb = ia.values.get("h_tilde", np.nan), ib.values.get("h_tilde", np.nan)
        du = float(np.max(np.abs(ua - ub))); dh = abs(ha - hb) / (1 + abs(hb))
        if ia.status != ib.status or du > 1e-4 or not dh <= 1e-5:
            diffs.append((r, k, np.round(x, 4), ia.status, ib.status, ua, ub, ha, hb))
            break
        worst_u, worst_h = max(worst_u, du), max(worst_h, dh)
        w = s.W.sample(1, rng)[0]
        x = system.step(x, ua, w); xb = system.step(xb, ub, w)
print(f"loops agreeing until a difference: worst |du| {worst_u:.1e}, rel h_tilde {worst_h:.1e}; loops with a difference: {len(diffs)}")
for dd in diffs: print(dd)
