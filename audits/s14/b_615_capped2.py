"""Audit B: (6.15) from states outside S_r on the §5.6 example, SQP capped; statuses."""
import sys
import warnings

import numpy as np

from balustrade.backends.targets import PRESETS
from balustrade.control.multiobjective import MultiobjectivePCBFController
from balustrade.design.rpi import ellipsoidal_rpi
from balustrade.design.terminal_cbf import synthesize_terminal_cbf
from balustrade.dsl.policies import AffinePolicy
from balustrade.models.unstable2d import W_BOUND, unstable2d, unstable2d_setup

N = int(sys.argv[1]) if len(sys.argv) > 1 else 10
caps = [int(c) for c in sys.argv[2].split(",")] if len(sys.argv) > 2 else [1, 3, 8]
budget = len(sys.argv) > 3 and sys.argv[3] == "budget"
import os

RS = bool(os.environ.get("RS"))
system, s = unstable2d(), unstable2d_setup(N)
error = ellipsoidal_rpi(system.A, system.B, s.W, s.X, s.U)
X_E, U_E = error.tighten_state(s.X), error.tighten_input(s.U)
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    cbf = synthesize_terminal_cbf(system.A, system.B, X_E, U_E, delta_N=s.deltas()[-1])
rng = np.random.default_rng(3)
starts = [np.array(s.x0)] if len(sys.argv) > 4 else [np.array([0.95, 3.0]), *rng.uniform([-0.8, -5.0], [0.8, 5.0], (3, 2))]
for cap in caps:
    tgt = PRESETS["robust-sqp"].with_options({"max_iter": cap})
    if budget:
        tgt = PRESETS["robust-sqp"].with_budget(iterations=cap).with_retries(
            PRESETS["robust-sqp"].retry_chain())
    ctrl = MultiobjectivePCBFController.build(system, s.X, s.U, cbf, AffinePolicy(cbf.K), N,
                                              s.deltas(), error, s.alpha_f, target=tgt,
                                              slack_target="robust-sqp", running_sum=RS)
    print("cap", cap, tgt)
    for x in starts:
        ctrl.reset()
        for k in range(6):
            u, info = ctrl.step(x, [2.5])
            sol = info.solutions.get("problem")
            print(" ", k, np.round(x, 4), info.status, info.fallback,
                  {kk: float(f"{v:.6g}") for kk, v in info.values.items()},
                  sol.status, sol.raw.get("function"), sol.message)
            x = system.step(x, u, W_BOUND * np.ones(2))
