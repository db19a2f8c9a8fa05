"""Audit A: maximize_quadratic_on_ball (the exact certificate of (3.19)/(3.28)) near the hard case:
attained value vs its dual bound vs an independent dense-grid/SDP value."""
import cvxpy as cp
import numpy as np

from balustrade.problems.regret.verify import maximize_quadratic_on_ball

rng = np.random.default_rng(0); worst_gap = 0; worst_own = 0
for trial in range(300):
    k = rng.integers(2, 7); Q, _ = np.linalg.qr(rng.standard_normal((k, k)))
    alpha = np.sort(rng.standard_normal(k))
    if trial % 3 == 0: alpha[-2] = alpha[-1]      # repeated top eigenvalue
    A = Q @ np.diag(alpha) @ Q.T
    beta = rng.standard_normal(k) * rng.choice([1, 1e-3, 1e-6, 1e-9, 0.0], size=k)
    top = alpha >= alpha[-1] - 1e-12
    beta[top] *= rng.choice([1, 1e-5, 1e-8, 1e-12, 0.0])
    b = Q @ beta; c = rng.standard_normal(); om = float(rng.uniform(0.1, 5))
    r = maximize_quadratic_on_ball(A, b, c, om)
    assert r.w @ r.w <= om * (1 + 1e-9), (trial, r.w @ r.w, om)
    gap = (r.upper - r.value) / max(1, abs(r.upper)); worst_gap = max(worst_gap, gap)
    t = cp.Variable(); lam = cp.Variable(nonneg=True)
    L = cp.bmat([[cp.reshape(t - c - lam * om, (1, 1)), -b.reshape(1, k)], [-b.reshape(k, 1), lam * np.eye(k) - A]])
    pr = cp.Problem(cp.Minimize(t), [(L + L.T) / 2 >> 0]); pr.solve(solver="CLARABEL")
    d = (pr.value - r.value) / max(1, abs(pr.value)); worst_own = max(worst_own, d)
    if gap > 1e-8 or d > 1e-7:
        g2 = np.random.default_rng(trial)
        Wb = g2.standard_normal((50000, k)); Wb *= np.sqrt(om) / np.linalg.norm(Wb, axis=1, keepdims=True)
        sm = (np.einsum("ij,jk,ik->i", Wb, A, Wb) + 2 * Wb @ b + c).max()
        print(trial, "value", r.value, "upper", r.upper, "own SDP", pr.value, pr.status, "sampled", sm, "hard", r.hard_case, "alpha", np.round(alpha, 3), "beta", beta)
print("worst (upper-value)/|upper|", worst_gap, "worst (own-value)/|own|", worst_own)
