"""Audit B: independent cvxpy (5.15) on the §5.6 example (N=10): is (6.15) infeasible where IPOPT
says so?  (6.15) is feasible iff h_r(x) <= bound.  Data from the repo only for E (ellipsoid),
K_E, P_f; tightenings recomputed here from support functions."""
import warnings

import cvxpy as cp
import numpy as np

from balustrade.control.multiobjective import MultiobjectivePCBFController
from balustrade.design.rpi import ellipsoidal_rpi
from balustrade.design.terminal_cbf import synthesize_terminal_cbf, terminal_cbf_with_domain
from balustrade.dsl.policies import AffinePolicy
from balustrade.models.unstable2d import W_BOUND, A, B, unstable2d, unstable2d_setup

N = 10
system, s = unstable2d(), unstable2d_setup(N)
error = ellipsoidal_rpi(system.A, system.B, s.W, s.X, s.U)
PE = error.E.P
Sig = np.linalg.inv(PE)
sup = lambda a: float(np.sqrt(a @ Sig @ a))
Hx = np.vstack([np.eye(2), -np.eye(2)]); bx = np.array([1, 10, 1, 10.0])
Hu = np.array([[1.0], [-1.0]]); bu = np.array([2.5, 2.5])
bxE = bx - np.array([sup(r) for r in Hx])
buE = bu - np.array([sup(error.K.T @ r) for r in Hu])
deltas = s.deltas()
X_E, U_E = error.tighten_state(s.X), error.tighten_input(s.U)
assert np.allclose(X_E.h, bxE) and np.allclose(U_E.h, buE), (X_E.h, bxE, U_E.h, buE)

def h_r(x, Pf, alpha_f=s.alpha_f):
    z = cp.Variable((2, N + 1)); v = cp.Variable((1, N)); xi = cp.Variable((4, N), nonneg=True)
    xiN = cp.Variable(nonneg=True)
    e = x - z[:, 0]
    cons = [cp.quad_form(e, PE) <= 1, z[:, 1:] == A @ z[:, :-1] + B @ v,
            Hu @ v <= buE[:, None]]
    cons += [Hx @ z[:, i] - bxE + deltas[i] <= xi[:, i] for i in range(N)]
    cons += [cp.quad_form(z[:, N], Pf) - 1 <= xiN]
    p = cp.Problem(cp.Minimize(alpha_f * xiN + cp.sum(xi)), cons)
    p.solve(solver="CLARABEL")
    return p.value, p.status

for label, make in [("printed SDP (gamma_f~0)", lambda: synthesize_terminal_cbf(
        A, B, X_E, U_E, delta_N=deltas[-1])),
                    ("with domain level 1", lambda: terminal_cbf_with_domain(
        A, B, X_E, U_E, deltas[-1], level=1.0))]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cbf = make()
    print("==", label, "gamma_f", cbf.gamma_f, "alpha_f*gamma_f", s.alpha_f * cbf.gamma_f)
    ctrl = MultiobjectivePCBFController.build(system, s.X, s.U, cbf, AffinePolicy(cbf.K), N,
                                              deltas, error, s.alpha_f, target="exact",
                                              slack_target="exact")
    rng = np.random.default_rng(3)
    starts = [np.array([0.95, 3.0]), *rng.uniform([-0.8, -5.0], [0.8, 5.0], (3, 2))]
    for x in starts:
        ctrl.reset()
        for k in range(5):
            u, info = ctrl.step(x, [2.5])
            hr, st = h_r(x, cbf.P)
            b = info.values["bound"]
            print(f"  k={k} x={np.round(x,4)} h_r(cvxpy)={hr:.6g} bound={b:.6g} "
                  f"h_cand={info.values['h_cand']:.6g} feasible615={hr <= b * (1 + 1e-7)} "
                  f"in D_r={hr <= s.alpha_f * cbf.gamma_f} -> {info.status}")
            x = system.step(x, u, W_BOUND * np.ones(2))
