"""Audit D: the seed-0 Python runs of the quick lane change (200 steps, converging config),
their must-show numbers recomputed from the trajectories with own formulas, against
/tmp/audit_d/lane/metrics.json."""
import json

import numpy as np

from balustrade.reproduce import lane_change as lc

m = json.load(open("/tmp/audit_d/lane/metrics.json"))["python_seed0"]
d = lc.design(lc.config("converging"))
ws = lc.disturbances(d, 0, lc.STEPS)
DEG = np.pi / 180
lo = np.array([-0.2, -35 * DEG, 0.5, -35 * DEG]); hi = np.array([0.2, 35 * DEG, 1.3, 35 * DEG])
for key, ctrl, hk in (("robust", lc.controllers(d, record_h_r=True)["robust"], "h_r"),
                      ("multiobjective", lc.multiobjective(d, 0.5), "h_tilde")):
    r = lc.closed_loop(ctrl, d, ws)
    X, h = r["states"], r[hk]
    inX = np.all((X >= lo - 1e-6) & (X <= hi + 1e-6), axis=1)
    entry = int(np.flatnonzero(h <= 1e-6)[0]) if np.any(h <= 1e-6) else -1
    peak = float(np.max(np.abs(X[:, 2] ** 2 * np.tan(X[:, 3]) / 0.09)))
    own = {"entered_S_r_at": entry, "X_kept_after_S_r": bool(entry < 0 or inX[entry:].all()),
           "final_p_y": float(X[-1, 0]), "peak_lateral_acceleration": peak,
           "non_increasing": bool(np.all(np.diff(h[np.isfinite(h)]) <= 2e-9 * np.maximum(1, np.abs(h[np.isfinite(h)][:-1])) + (1e-6 if key == 'robust' else 0))),
           "converged": bool(abs(X[-1, 0]) <= 0.2 and h[-1] <= 1e-6)}
    rep = m[key]
    print(key, {k: (own[k], rep[k]) for k in own})
    print("  steps outside X after entering S_r:", int((~inX[entry:]).sum()) if entry >= 0 else None,
          "| |u| within U:", bool(np.all(np.abs(r["inputs"][:, 0]) <= 17.5 * DEG + 1e-9) and np.all(np.abs(r["inputs"][:, 1]) <= 2 + 1e-9)))
