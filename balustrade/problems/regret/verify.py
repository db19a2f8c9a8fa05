"""Solver-independent certificates of worst-case regret (SPEC 4, items 15, 17, 18).

* :func:`worst_case_regret_energy` solves the trust-region subproblem (3.18) exactly:
  ``max_{‖w‖² ≤ ω} δᵀMδ`` with ``M = ΦᵀCΦ − 𝒪`` computed from the responses (not from the
  compressed factor used by the SDPs), by an eigendecomposition and the secular equation,
  including the "hard case". It returns the maximizer and a matching dual upper bound.
* :func:`pointwise_regret_lower_bound` maximizes the same convex quadratic over the product of
  ellipsoids {w_kᵀPw_k ≤ 1} by multi-start conditional-gradient ascent. Every value it
  reports is attained by a feasible disturbance (a certified lower bound on R⁰_PWB).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

from balustrade._checks import as_vector, check_psd
from balustrade.errors import BalustradeError
from balustrade.problems.regret.operators import Operators


def regret_matrix(ops: Operators, Phi_u: np.ndarray) -> np.ndarray:
    """M = ΦᵀCΦ − 𝒪 of the achievable Φ with input responses Φ_u (the regret is δᵀMδ)."""
    Phi_x = ops.phi_x(Phi_u)
    M = ops.cost_matrix(Phi_x, Phi_u) - ops.O
    return 0.5 * (M + M.T)


@dataclass(frozen=True)
class TrustRegionCertificate:
    value: float          # δ*ᵀMδ* at the computed maximizer (a lower bound, attained)
    upper: float          # dual bound c + νω + bᵀ(νI − A)⁺b (an upper bound)
    w: np.ndarray         # maximizer, ‖w‖² = ω
    nu: float             # multiplier of ‖w‖² ≤ ω
    hard_case: bool


def maximize_quadratic_on_ball(A: np.ndarray, b: np.ndarray, c: float, omega: float
                               ) -> TrustRegionCertificate:
    """max wᵀAw + 2bᵀw + c over ‖w‖² ≤ ω for symmetric A (the trust-region subproblem).

    Optimality: (νI − A)w = b, νI − A ⪰ 0, ν ≥ 0, ν(ω − ‖w‖²) = 0. With A = V diag(α) Vᵀ and
    β = Vᵀb: for A ≺ 0 with ‖A⁻¹b‖² ≤ ω the optimum is interior, ν = 0; otherwise ν solves the
    secular equation Σ β_i²/(ν − α_i)² = ω on ν > max(α_max, 0), or, in the hard case (β
    vanishing on the top eigenspace, α_max ≥ 0 and the equation unsolvable), ν = α_max and
    the top eigenvector fills up the norm.
    """
    if omega <= 0:
        raise BalustradeError(f"omega: must be positive, got {omega}")
    alpha, V = np.linalg.eigh(0.5 * (A + A.T))
    beta = V.T @ b
    amax = float(alpha[-1])
    scale = max(1.0, float(np.max(np.abs(alpha))), float(np.linalg.norm(b)))
    top = alpha >= amax - 1e-12 * scale
    rest = ~top
    tiny = 1e-13 * scale

    def norm_at(nu: float) -> float:
        # ν rounded onto α_max in the near-hard case gives β²/0 = inf: "outside the ball",
        # which keeps the bracket of the secular equation valid
        with np.errstate(divide="ignore"):
            return float(np.sqrt(np.sum(beta**2 / (nu - alpha) ** 2)))

    sqrt_om = np.sqrt(omega)
    beta_top = float(np.linalg.norm(beta[top]))
    hard = False
    if amax < -tiny and norm_at(0.0) <= sqrt_om:
        # A ≺ 0 and the unconstrained maximizer −A⁻¹b lies in the ball: interior optimum with
        # ν = 0 (the multiplier of ‖w‖² ≤ ω must be ≥ 0, so ν = α_max < 0 is not a solution)
        nu = 0.0
        v = beta / (nu - alpha)
        w = V @ v
        value = float(w @ A @ w + 2 * b @ w + c)
        upper = float(c + np.sum(beta ** 2 / (nu - alpha)))
        return TrustRegionCertificate(value, max(upper, value), w, nu, False)
    if beta_top <= tiny and amax >= -tiny:
        base = np.zeros_like(beta)
        base[rest] = beta[rest] / (amax - alpha[rest]) if np.any(rest) else 0.0
        if float(np.linalg.norm(base)) <= sqrt_om:
            hard = True
            nu = amax
            v = base.copy()
            idx = np.flatnonzero(top)[0]
            v[idx] = np.sqrt(max(omega - float(v @ v), 0.0))
    if not hard:
        lo = amax + max(tiny, 1e-15)
        hi = amax + float(np.linalg.norm(beta)) / sqrt_om + tiny
        while norm_at(lo) < sqrt_om:     # β_top tiny but nonzero: move lo closer
            lo = amax + (lo - amax) * 1e-3
            if lo - amax < 1e-300:
                break
        f = lambda nu: 1.0 / max(norm_at(nu), 1e-300) - 1.0 / sqrt_om
        nu = brentq(f, lo, hi, xtol=1e-15 * max(1.0, abs(amax)), rtol=1e-15, maxiter=500) \
            if f(lo) < 0 < f(hi) else hi
        v = beta / (nu - alpha)
        v = _fill_top(v, beta, top, omega, lambda u: _quad(alpha, beta, c, u))
    w = V @ v
    value = float(w @ A @ w + 2 * b @ w + c)
    # dual bound: for ν ≥ α_max, max ≤ c + νω + Σ β_i²/(ν − α_i) over the range of νI − A
    gap = nu - alpha
    safe = gap > tiny
    upper = float(c + nu * omega + np.sum(beta[safe] ** 2 / gap[safe]))
    return TrustRegionCertificate(value, upper, w, float(nu), hard)


def _quad(alpha: np.ndarray, beta: np.ndarray, c: float, v: np.ndarray) -> float:
    """vᵀdiag(α)v + 2βᵀv + c: the trust-region objective in eigen-coordinates."""
    return float(alpha @ v**2 + 2 * beta @ v + c)


def _fill_top(v: np.ndarray, beta: np.ndarray, top: np.ndarray, omega: float, objective
              ) -> np.ndarray:
    """Near the hard case (β tiny on the top eigenspace) ν − α_max is below the resolution of
    the secular equation and v falls short of the boundary; the maximizer is then v with its
    top-eigenspace part set so that ‖v‖² = ω (sign of β kept). The filled point is used when v
    is outside the ball (rounding of ν) or when it is better; the value stays attained."""
    rest_sq = float(v[~top] @ v[~top])
    room = omega - rest_sq
    if room <= 0.0:
        return v
    direction = v[top] if np.any(v[top]) else np.sign(beta[top]) + (beta[top] == 0)
    filled = v.copy()
    filled[top] = direction / np.linalg.norm(direction) * np.sqrt(room)
    outside = float(v @ v) > omega
    return filled if outside or objective(filled) > objective(v) else v


def worst_case_regret_energy(ops: Operators, Phi_u: np.ndarray, x0: object, omega: float
                             ) -> TrustRegionCertificate:
    """Exact worst-case regret (3.8)/(3.18) of the responses Φ_u for fixed x₀ and ‖w‖² ≤ ω."""
    x0v = as_vector(x0, "x0", ops.n)
    return _max_over_energy_ball(regret_matrix(ops, Phi_u), x0v, omega)


def _max_over_energy_ball(D: np.ndarray, x0v: np.ndarray, omega: float
                          ) -> TrustRegionCertificate:
    """max δᵀDδ over δ = (x₀, w), ‖w‖² ≤ ω, for a δ-space matrix D and fixed x₀."""
    n = x0v.size
    return maximize_quadratic_on_ball(D[n:, n:], D[n:, :n] @ x0v, float(x0v @ D[:n, :n] @ x0v),
                                      float(omega))


def generalized_level_energy(ops: Operators, Phi_u: np.ndarray, x0: object, omega: float,
                             W: np.ndarray, rtol: float = 1e-10, guess: float | None = None
                             ) -> float:
    """Exact generalized regret level (3.28) of the responses Φ_u over ‖w‖² ≤ ω, fixed x₀:
    the smallest μ with max_w δᵀ(M − μW)δ ≤ 0, by bisection on μ over exact trust-region
    solutions (the maximum is decreasing in μ for W ≻ 0). Independent of any SDP solver;
    ``guess`` (e.g. the SDP's level) only narrows the first bracket to ±1e-6 around it when
    the bracket holds (15 trust-region solves instead of ≈ 40)."""
    x0v = as_vector(x0, "x0", ops.n)
    Wm = np.asarray(W, dtype=float)
    M = regret_matrix(ops, Phi_u)

    def worst(mu: float) -> float:
        return _max_over_energy_ball(M - mu * Wm, x0v, omega).value

    lo, hi = 0.0, 1.0
    if guess is not None and np.isfinite(guess) and guess > 0:
        hi = guess * (1 + 1e-6)
        if worst(guess * (1 - 1e-6)) > 0.0:
            lo = guess * (1 - 1e-6)
    while worst(hi) > 0.0:
        lo, hi = hi, 2.0 * hi
        if hi > 1e15:
            raise BalustradeError("generalized_level_energy: level above 1e15 (W singular?)")
    while hi - lo > rtol * max(hi, 1e-300):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if worst(mid) > 0.0 else (lo, mid)
    return hi


@dataclass(frozen=True)
class PointwiseLowerBound:
    value: float          # best objective found, attained by ``w`` (a certified lower bound)
    w: np.ndarray         # (T, p) with w_kᵀPw_k ≤ 1
    starts: int


def pointwise_regret_lower_bound(ops: Operators, Phi_u: np.ndarray, x0: object, P: object,
                                 W: np.ndarray | None = None, starts: int = 40,
                                 iters: int = 300, seed: int = 0) -> PointwiseLowerBound:
    """Lower bound on max over w_kᵀPw_k ≤ 1 of δᵀMδ (W None) or of δᵀMδ / δᵀWδ.

    Conditional-gradient ascent in v_k = P^{1/2}w_k (a product of unit balls): each step moves
    every block to the maximizer of the linearization, v_k = g_k/‖g_k‖, which never decreases a
    convex objective. For the ratio, the same steps run on δᵀ(M − ρW)δ with ρ updated to the
    current ratio (Dinkelbach). Starts: random boundary points, top eigenvectors, constant signs.
    """
    x0v = as_vector(x0, "x0", ops.n)
    Pm = check_psd(np.asarray(P, dtype=float), "P", strict=True)
    T, p, n = ops.T, ops.p, ops.n
    lam, U = np.linalg.eigh(Pm)
    P_mhalf = (U / np.sqrt(lam)) @ U.T
    Lmap = np.kron(np.eye(T), P_mhalf)            # w = Lmap v
    M = regret_matrix(ops, Phi_u)
    Wm = None if W is None else np.asarray(W, dtype=float)
    rng = np.random.default_rng(seed)

    def objective(v: np.ndarray) -> float:
        d = np.concatenate([x0v, Lmap @ v])
        num = float(d @ M @ d)
        return num if Wm is None else num / float(d @ Wm @ d)

    def normalize(v: np.ndarray) -> np.ndarray:
        blocks = v.reshape(T, p)
        norms = np.linalg.norm(blocks, axis=1, keepdims=True)
        fill = rng.standard_normal(blocks.shape)
        fill /= np.linalg.norm(fill, axis=1, keepdims=True)
        return np.where(norms > 1e-14, blocks / np.maximum(norms, 1e-300), fill).reshape(-1)

    Mw = Lmap.T @ M[n:, n:] @ Lmap
    mx = Lmap.T @ M[n:, :n] @ x0v
    if Wm is not None:
        Ww = Lmap.T @ Wm[n:, n:] @ Lmap
        wx = Lmap.T @ Wm[n:, :n] @ x0v
    inits = [normalize(rng.standard_normal(T * p)) for _ in range(max(starts - 3, 1))]
    top = np.linalg.eigh(Mw)[1][:, -1]
    inits += [normalize(top), normalize(-top), normalize(mx if np.any(mx) else top)]
    best_val, best_v = -np.inf, inits[0]
    for v in inits:
        val = objective(v)
        for _ in range(iters):
            if Wm is None:
                g = Mw @ v + mx
            else:
                rho = val
                g = (Mw - rho * Ww) @ v + (mx - rho * wx)
            v_new = normalize(g)
            val_new = objective(v_new)
            if val_new <= val * (1 + 1e-13) + 1e-300:
                if val_new > val:
                    v, val = v_new, val_new
                break
            v, val = v_new, val_new
        if val > best_val:
            best_val, best_v = val, v
    w = (Lmap @ best_v).reshape(T, p)
    return PointwiseLowerBound(float(best_val), w, len(inits))


# ---------------------------------------------------------------------------------------------
# exact levels of a controller for the energy-bound and adversarial problems (certificates of
# the syntheses, see control.regret_synthesis.SynthesisResult.info["certificate"])
# ---------------------------------------------------------------------------------------------
def adversarial_level(ops: Operators, Phi_u: np.ndarray) -> float:
    """(3.24): ‖ΦᵀCΦ − 𝒪‖₂ of the responses Φ_u (M ⪰ 0, so its largest eigenvalue)."""
    return float(np.linalg.eigvalsh(regret_matrix(ops, Phi_u))[-1])


def hinf_level(ops: Operators, Phi_u: np.ndarray) -> float:
    """SH∞: λ_max(ΦᵀCΦ) on the whole δ, the squared ℓ₂ gain of the closed loop."""
    C = ops.cost_matrix(ops.phi_x(Phi_u), Phi_u)
    return float(np.linalg.eigvalsh(0.5 * (C + C.T))[-1])


def weighted_level(M: np.ndarray, W: np.ndarray) -> float:
    """min μ with μW − M ⪰ 0 for W ≻ 0: λ_max(W^{-1/2}MW^{-1/2}) ((3.29)/(3.30))."""
    lam, U = np.linalg.eigh(0.5 * (W + W.T))
    Wmh = (U / np.sqrt(lam)) @ U.T
    K = Wmh @ M @ Wmh
    return float(np.linalg.eigvalsh(0.5 * (K + K.T))[-1])


def zero_x0_level(ops: Operators, Phi_u: np.ndarray, W: np.ndarray,
                  adversarial_x0: bool = False) -> float:
    """(3.29)/(3.30): the tight level of Φ_u for x₀ = 0 (w-blocks of M and W) or, with
    ``adversarial_x0``, on the whole δ."""
    M = regret_matrix(ops, Phi_u)
    if adversarial_x0:
        return weighted_level(M, W)
    return weighted_level(ops.partition(M)[2], ops.partition(W)[2])
