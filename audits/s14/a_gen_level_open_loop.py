"""Audit A: the exact-level certificates of a given controller (verify.py) when the inner max is
interior: the open-loop Φ_u = 0 (u ≡ 0) of a stable system, large x0, small ω, W = I and 𝒪.
Own level: S-lemma SDP per μ (λ ≥ 0 free to be 0), bisection."""
import warnings

import cvxpy as cp
import numpy as np

from balustrade.problems.regret import LTVSystem, build_operators
from balustrade.problems.regret.verify import (
    generalized_level_energy,
    maximize_quadratic_on_ball,
    regret_matrix,
    worst_case_regret_energy,
)

warnings.filterwarnings("ignore")
def own_worst(D, x0, om):
    n = x0.size; Dww, Dwx, c = D[n:, n:], D[n:, :n] @ x0, x0 @ D[:n, :n] @ x0; k = Dww.shape[0]
    t = cp.Variable(); lam = cp.Variable(nonneg=True)
    L = cp.bmat([[cp.reshape(t - c - lam * om, (1, 1)), -Dwx.reshape(1, k)], [-Dwx.reshape(k, 1), lam * np.eye(k) - Dww]])
    cp.Problem(cp.Minimize(t), [(L + L.T) / 2 >> 0]).solve(solver="CLARABEL", tol_gap_abs=1e-12, tol_gap_rel=1e-12, tol_feas=1e-12)
    return t.value
def own_level(M, W, x0, om):
    lo, hi = 0.0, 1.0
    while own_worst(M - hi * W, x0, om) > 0: lo, hi = hi, 2 * hi
    for _ in range(45):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if own_worst(M - mid * W, x0, om) > 0 else (lo, mid)
    return hi
print("plain case: max of -|w|^2 + 1 over |w|^2 <= 2 (true 1 at w=0):",
      maximize_quadratic_on_ball(-np.eye(2), np.zeros(2), 1.0, 2.0))
A = np.array([[0.5, 0.2], [0.0, 0.6]]); B = np.array([[0.0], [1.0]])
ops = build_operators(LTVSystem.create(A, B, 4))
Phi_u = np.zeros((ops.m * (ops.T + 1), ops.nd))      # u ≡ 0, causal
x0 = np.array([5.0, -3.0]); om = 1e-2
M = regret_matrix(ops, Phi_u)
for Wn, Wm in (("I", np.eye(ops.nd)), ("O", ops.O)):
    mine = generalized_level_energy(ops, Phi_u, x0, om, Wm)
    own = own_level(M, Wm, x0, om)
    print(f"W={Wn}: generalized_level_energy {mine:.8g}  own {own:.8g}  (package/own - 1 = {mine/own-1:.2e})")
print("worst_case_regret_energy(u≡0).upper", worst_case_regret_energy(ops, Phi_u, x0, om).upper, "own", own_worst(M, x0, om))
# a controller good for w, bad for x0: interior inner maximum at the level (μ W_ww ≻ M_ww)
from balustrade.control.regret_synthesis import zero_x0_regret

base = zero_x0_regret(ops, W="I").Phi_u.copy()
rng = np.random.default_rng(0)
for scale in (1.0, 3.0, 10.0):
    Pu = base.copy(); Pu[:, :ops.n] += scale * rng.standard_normal((Pu.shape[0], ops.n))
    M = regret_matrix(ops, Pu)
    for om in (1.0, 100.0):
        for Wn, Wm in (("I", np.eye(ops.nd)), ("O", ops.O)):
            mine = generalized_level_energy(ops, Pu, x0, om, Wm); own = own_level(M, Wm, x0, om)
            lam = np.linalg.eigvalsh((M - own * Wm)[ops.n:, ops.n:]).max()
            print(f"scale {scale} ω={om} W={Wn}: package {mine:.8g} own {own:.8g} rel {mine/own-1:+.2e}  λmax(A_ww) at level {lam:.3g}")
