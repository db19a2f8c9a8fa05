"""Audit B: the IPOPT retry of robust-sqp's (6.15) chain, run alone cold (lead) and from the
candidate, at the states of a closed loop of the §5.6 example from x0 (N=100)."""
import sys
import warnings

import numpy as np

from balustrade.backends import compile
from balustrade.control.multiobjective import MultiobjectivePCBFController
from balustrade.design.rpi import ellipsoidal_rpi
from balustrade.design.terminal_cbf import synthesize_terminal_cbf
from balustrade.dsl.policies import AffinePolicy
from balustrade.models.unstable2d import W_BOUND, unstable2d, unstable2d_setup
from balustrade.problems.multiobjective import decrease_bound, multiobjective_pcbf_problem

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
rs = compile(ocp, "robust-sqp")
print("chain", rs.retries)
ip = [k for k, (nm, _) in enumerate(rs.retries) if nm == "ipopt"][0]
x = np.array(s.x0)
for k in range(4):
    u, info = ctrl.step(x, [2.5])
    x = system.step(x, u, W_BOUND * np.ones(2))
    c = ctrl.candidate
    bound = decrease_bound(ctrl.h_tilde(c.xi, c.xi_N), float(ctrl.h_prev), ctrl.rho)
    bound += ctrl.bound_tol * max(1.0, abs(bound))
    prm = {"x0": x, "u_p": [2.5], "bound": bound}
    led = rs.with_retries([rs.retries[ip]]).solve(prm, lead=0) if False else None
    only = rs.with_retries([])  # placeholder
    cold = rs._solve_with(rs._retry_solvers()[ip], rs.ocp.pack_parameters(prm),
                          rs._initial_guess(None, rs.ocp.pack_parameters(prm)))
    warm = rs._solve_with(rs._retry_solvers()[ip], rs.ocp.pack_parameters(prm),
                          rs._initial_guess(c.as_dict(), rs.ocp.pack_parameters(prm)))
    print(k + 1, np.round(x, 4), "bound", bound, "| IPOPT cold:", cold.status, cold.message[:60],
          cold.iterations, "| from candidate:", warm.status, warm.message[:60], warm.iterations,
          flush=True)
