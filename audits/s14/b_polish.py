"""Audit B: polished slacks min(ξ_sol, need(z)) vs need(z) alone vs an independent cvxpy h_r
on (5.15) of the §5.6 example (N=10), SQP and IPOPT targets."""
import importlib.util
import warnings

import numpy as np

from balustrade.backends import compile
from balustrade.control.robust_steps import minimal_slacks, polished_slacks, slack_cost
from balustrade.design.rpi import ellipsoidal_rpi
from balustrade.design.terminal_cbf import synthesize_terminal_cbf
from balustrade.models.unstable2d import unstable2d, unstable2d_setup
from balustrade.problems.robust import robust_pcbf_slack_problem

spec = importlib.util.spec_from_file_location("indep", str(__import__("pathlib").Path(__file__).with_name("b_615_indep.py")))

N = 10
system, s = unstable2d(), unstable2d_setup(N)
error = ellipsoidal_rpi(system.A, system.B, s.W, s.X, s.U)
X_E, U_E = error.tighten_state(s.X), error.tighten_input(s.U)
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    cbf = synthesize_terminal_cbf(system.A, system.B, X_E, U_E, delta_N=s.deltas()[-1])
ocp = robust_pcbf_slack_problem(system, s.X, s.U, cbf, N, s.deltas(), error, s.alpha_f, 1)
import cvxpy as cp

PE = error.E.P
def h_r(x):
    z = cp.Variable((2, N + 1)); v = cp.Variable((1, N)); xi = cp.Variable((4, N), nonneg=True)
    xiN = cp.Variable(nonneg=True); e = x - z[:, 0]
    cons = [cp.quad_form(e, PE) <= 1, z[:, 1:] == system.A @ z[:, :-1] + system.B @ v,
            U_E.H @ v <= U_E.h[:, None]]
    cons += [X_E.H @ z[:, i] - X_E.h + s.deltas()[i] <= xi[:, i] for i in range(N)]
    cons += [cp.quad_form(z[:, N], cbf.P) - 1 <= xiN]
    p = cp.Problem(cp.Minimize(s.alpha_f * xiN + cp.sum(xi)), cons)
    p.solve(solver="CLARABEL", tol_gap_abs=1e-12, tol_gap_rel=1e-12, tol_feas=1e-12)
    return p.value
rng = np.random.default_rng(4)
for tgt in ("robust-sqp", "exact"):
    c = compile(ocp, tgt)
    worst_pol, worst_need, n = 0.0, 0.0, 0
    for x in rng.uniform([-0.9, -2.0], [0.9, 2.0], (25, 2)):
        sol = c.solve({"x0": x})
        if not sol.success:
            continue
        n += 1
        xi_p, xN_p = polished_slacks(sol, X_E, cbf, s.deltas())
        xi_m, xN_m = minimal_slacks(X_E, cbf, s.deltas(), sol["z"])
        hp, hm, ht = slack_cost(xi_p, xN_p, s.alpha_f), slack_cost(xi_m, xN_m, s.alpha_f), h_r(x)
        worst_pol = min(worst_pol, (hp - ht) / max(1, ht))
        worst_need = min(worst_need, (hm - ht) / max(1, ht))
        if hp < hm - 1e-12 * max(1, hm):
            print(f"  {tgt} x={np.round(x,3)} polished {hp:.12g} < need(z) {hm:.12g} (true h_r {ht:.12g})")
    print(tgt, n, "states; most negative (h̃ - h_r)/max(1,h_r): polished", worst_pol, "need(z)", worst_need)
