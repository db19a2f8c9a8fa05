"""The 𝒪 weight through its LQ definition: lifted (x, u) coordinates (issue #12, item 2).

With W_w = 𝒪 the regret LMIs (3.28), (3.30), (3.32) contain the term μ δᵀ𝒪δ with the dense
𝒪 of (3.6). Its banded lowering whitened 𝒪 (δ = Bη with B = chol(𝒪⁻¹), cond B = √cond 𝒪)
and was ill-conditioned (:mod:`balustrade.backends.lmi_banded`). This module states the same
term without 𝒪: by (3.4)/(3.6), δᵀ𝒪δ = J*(δ) = min_u J(u, δ), the value of an LQ problem whose
constraint, the dynamics, is block bidiagonal.

**Coordinates.** Write the arrow LMI of the problem as a quadratic form in ζ = (α, w) (α the
homogenizing scalar of the x₀ row, δ = (αx₀, w); ζ = w for (3.30)): it is
μ·q(ζ) + r(ζ) − ‖ỹ(ζ)‖² ≥ 0 for all ζ, with q(ζ) = δᵀ𝒪δ, r the multiplier terms and ỹ the
regret rows [y, L]. Let ξ = (v₀, x₁, v₁, x₂, …, v_{T−1}, x_T) (blocks ξ_k = (v_k, x_{k+1}) of
size m + n) and x₀ = αx₀. Since every E_k is invertible (SPEC 2.8), (α, ξ) ↦ (α, w) with

    w_k = E_k⁻¹(x_{k+1} − A_kx_k − B_kv_k),        i.e.  w = N ξ + n_α α,

is onto, and for fixed (α, w) the fibre is parametrized by v (x is then the state trajectory
of (3.1) under the input v and disturbance w). N is block lower bidiagonal (w_k reads ξ_k and
the x_k of ξ_{k−1}); n_α = (−E₀⁻¹A₀x₀, 0, …). Along the fibre
k₀α² + ξᵀ𝒦ξ = Σ_t x_tᵀQ_tx_t + Σ_{t<T} v_tᵀR_tv_t = J(v, δ) (u_T = 0, which is optimal: u_T
moves no state), with 𝒦 = blkdiag(R₀, Q₁, …, R_{T−1}, Q_T) and k₀ = x₀ᵀQ₀x₀, so

    q(ζ) = min { k₀α² + ξᵀ𝒦ξ : Nξ + n_αα = w }.                                    (★)

**Claim.** For μ ≥ 0 the LMI holds iff the lifted form
μ(k₀α² + ξᵀ𝒦ξ) + r(ζ(α, ξ)) − ‖ỹ(ζ(α, ξ))‖² ≥ 0 holds for all (α, ξ) — an arrow LMI in
(α, ξ) with D' = μ𝒦 + NᵀD_rN (block diagonal plus block tridiagonal: no dense weight), b' =
Nᵀ(b_r + D_rn_α), a' = μk₀ + a_r + 2b_rᵀn_α + n_αᵀD_rn_α, y' = y + Ln_α, L' = LN.
*Proof.* (⇐) Given ζ, take ξ attaining the minimum (★) (a convex quadratic bounded below
on an affine set attains it): the lifted form there is μq(ζ) + r(ζ) − ‖ỹ(ζ)‖². (⇒) For any
(α, ξ) with ζ = ζ(α, ξ), μ(k₀α² + ξᵀ𝒦ξ) ≥ μq(ζ) since μ ≥ 0. ∎
The lifted LMI implies μ ≥ 0 by itself (along a fibre direction f ≠ 0, Nf = 0, the form is
μfᵀ𝒦f·t² + O(t) and fᵀ𝒦f > 0 because f moves v and R ≻ 0). The original LMIs imply μ ≥ 0
whenever J* ≢ 0 on the disturbance set: at α = 1 and an admissible w the form reads
μJ*(δ) ≥ (J − J*)(δ) + (non-negative multiplier terms) ≥ 0. So the two SDPs have the same
feasible set and the same optimum; :func:`lq_lift` is only declared when 𝒪₃ ≠ 0.

The regret rows L' = LN keep their structure: the free part stays causal (w_k reads ξ_{k−1},
ξ_k), and the constant part is still semiseparable (its Hankel blocks are those of L times
blocks of N), so the semiseparable coordinates of :mod:`balustrade.backends.lmi_banded` apply
with blocks of m + n — without any whitening of 𝒪. This module states the data (numpy only);
the lowering is in :mod:`balustrade.backends.synthesis_structured`.

Declared by (3.28), (3.30) and (3.32) with W_w = "O"; used by ``lmi="lifted"`` (not the
default: measured no better than the whitened banded form, and worse for (3.32) at T = 25 —
the solver stalls in the semiseparable coordinates on ξ; docs/regret.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from balustrade.problems.regret.operators import Operators


@dataclass(frozen=True)
class LQLift:
    """(★) as data for an arrow LMI over the w-columns (module docstring).

    ``coef`` multiplies the LQ term (μ); the D term ``dense`` and the b term ``b_dense`` (None
    if none) are the ones it replaces, ``a_rest`` is the scalar a without its μ part (None if
    the LMI has no scalar row). ``N`` (pT × T(m+n)), ``n_alpha`` (pT), ``K`` (block diagonal),
    ``k0``; ``block`` = m + n, the size of the blocks of ξ.
    """

    coef: object
    dense: int
    b_dense: int | None
    a_rest: object | None
    N: np.ndarray
    n_alpha: np.ndarray
    K: np.ndarray
    k0: float
    block: int


def lq_maps(ops: Operators, x0: np.ndarray | None) -> tuple[np.ndarray, np.ndarray,
                                                               np.ndarray, float]:
    """(N, n_α, 𝒦, k₀) of (★): w = Nξ + n_αα and J = k₀α² + ξᵀ𝒦ξ (x₀ = αx₀; x₀ = 0 if None)."""
    sysm = ops.system
    n, m, p, T = ops.n, ops.m, ops.p, ops.T
    nb = m + n
    N = np.zeros((p * T, nb * T))
    K = np.zeros((nb * T, nb * T))
    n_alpha = np.zeros(p * T)
    for k in range(T):
        Einv = np.linalg.inv(sysm.E[k])
        rows = slice(k * p, (k + 1) * p)
        c = k * nb
        N[rows, c: c + m] = -Einv @ sysm.B[k]
        N[rows, c + m: c + nb] = Einv
        if k:
            N[rows, c - n: c] = -Einv @ sysm.A[k]
        elif x0 is not None:
            n_alpha[rows] = -Einv @ sysm.A[0] @ x0
        K[c: c + m, c: c + m] = sysm.R[k]
        K[c + m: c + nb, c + m: c + nb] = sysm.Q[k + 1]
    k0 = 0.0 if x0 is None else float(x0 @ sysm.Q[0] @ x0)
    return N, n_alpha, K, k0


def lq_lift(ops: Operators, x0: np.ndarray | None, coef: object, dense: int,
            b_dense: int | None = None, a_rest: object | None = None) -> LQLift | None:
    """The lifting of μ·δᵀ𝒪δ (δ = (αx₀, w)) for an arrow LMI over w, or None when 𝒪₃ = 0
    (then the original LMI need not imply μ ≥ 0, module docstring)."""
    if not np.any(ops.partition(ops.O)[2]):
        return None
    N, n_alpha, K, k0 = lq_maps(ops, x0)
    return LQLift(coef, dense, b_dense, a_rest, N, n_alpha, K, k0, ops.m + ops.n)


__all__ = ["LQLift", "lq_lift", "lq_maps"]
