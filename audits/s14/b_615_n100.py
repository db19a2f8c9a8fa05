"""Audit B: §5.6 example N=100 from x0=(0,1): is the candidate (6.14) feasible for (6.15)
(balustrade.verify, no solver), and what does IPOPT say from it / cold?"""
import sys
import warnings

import numpy as np

from balustrade import verify
from balustrade.backends import Solution, compile
from balustrade.control.multiobjective import MultiobjectivePCBFController
from balustrade.design.rpi import ellipsoidal_rpi
from balustrade.design.terminal_cbf import synthesize_terminal_cbf
from balustrade.dsl.policies import AffinePolicy
from balustrade.models.unstable2d import W_BOUND, unstable2d, unstable2d_setup
from balustrade.problems.multiobjective import multiobjective_pcbf_problem

N = int(sys.argv[1]) if len(sys.argv) > 1 else 100
system, s = unstable2d(), unstable2d_setup(N)
error = ellipsoidal_rpi(system.A, system.B, s.W, s.X, s.U)
X_E, U_E = error.tighten_state(s.X), error.tighten_input(s.U)
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    cbf = synthesize_terminal_cbf(system.A, system.B, X_E, U_E, delta_N=s.deltas()[-1])
ctrl = MultiobjectivePCBFController.build(system, s.X, s.U, cbf, AffinePolicy(cbf.K), N,
                                          s.deltas(), error, s.alpha_f, target="exact",
                                          slack_target="exact")
ocp = multiobjective_pcbf_problem(system, s.X, s.U, cbf, N, s.deltas(), error, s.alpha_f)
ipopt = compile(ocp, "exact")
x = np.array(s.x0)
for k in range(4):
    u, info = ctrl.step(x, [2.5])
    sol = info.solutions["problem"]
    print(k, x, info.status, info.values, sol.status, sol.message[:120])
    x = system.step(x, u, W_BOUND * np.ones(2))
    # the candidate for the next step, checked at the next state with the next bound
    c = ctrl.candidate
    h_cand = ctrl.h_tilde(c.xi, c.xi_N)
    from balustrade.problems.multiobjective import decrease_bound
    bound = decrease_bound(h_cand, float(ctrl.h_prev), ctrl.rho)
    bound += ctrl.bound_tol * max(1.0, abs(bound))
    start = c.as_dict()
    p = ocp.pack_parameters({"x0": x, "u_p": [2.5], "bound": bound})
    fake = Solution("feasible", float("nan"), {k_: np.asarray(v) for k_, v in start.items()}, {}, 0.0, 0,
                    "none", "none", p=p)
    try:
        rep = verify(ocp, fake, tol=1e-9)
        print("   candidate at next state:", rep)
    except Exception as e:
        print("   verify failed:", type(e).__name__, e)
    cold = ipopt.solve({"x0": x, "u_p": [2.5], "bound": bound})
    warm = ipopt.solve({"x0": x, "u_p": [2.5], "bound": bound}, warm_start=start)
    print("   IPOPT cold:", cold.status, cold.message[:80], "| from candidate:", warm.status, warm.message[:80])
