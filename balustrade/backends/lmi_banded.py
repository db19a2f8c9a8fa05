"""Banded coordinates for the regret LMIs: a congruence that gives them small chordal cliques.

Every synthesis LMI of Chapter 3 is, after the compression of
:mod:`balustrade.problems.regret.operators`, of the form (Schur complement form of (3.21),
rows: scalar a, disturbance coordinates, the M = m(T+1) rows of the regret factor
Y = S(Φ_u − Φ_u^nc))::

    ⎡ a   bᵀ  yᵀ ⎤
    ⎢ b   D   Lᵀ ⎥ ⪰ 0,      L = Y[:, cols] = X + L₀,   X causal (free),  L₀ constant.
    ⎣ y   L   I  ⎦

Its aggregate sparsity is dense: the constant L₀ = −SΦ_u^nc[:, cols] has a full anti-causal
part, and D = λI + μ𝒪 (competitive ratio, SH∞) is dense. A congruence with an invertible C,
``cols = C η``, replaces D by CᵀDC, L by LC and b by Cᵀb and is an exact reformulation. Two
facts of the LQ structure make a C with banded results exist:

* 𝒪⁻¹ is block tridiagonal. 𝒪 (3.6) is the quadratic form of the non-causal optimal cost,
  J*(δ) = min ‖C^{1/2}z‖² s.t. the dynamics (3.14) hold, whose value is
  δᵀℰᵀ(𝒟C⁻¹𝒟ᵀ)⁻¹ℰδ with the block-bidiagonal dynamics operator 𝒟 = [I − Z𝒜, −Zℬ]; so
  𝒪⁻¹ = ℰ⁻¹𝒟C⁻¹𝒟ᵀℰ⁻ᵀ (and the inverse of 𝒪's w-block is banded too). For a dense weight W
  with banded W⁻¹, B = its block-bidiagonal Cholesky factor (W⁻¹ = BBᵀ) gives BᵀWB = I and
  banded BᵀB, B·blockdiag·B, and XB stays causal.
* The anti-causal part of Φ_u^nc is semiseparable: its Hankel blocks L₀[u_{0..k}, δ_{>k}]
  have rank ≤ n (the non-causal optimal input reacts to the future only through the n-dim
  co-state of the LQ problem). With an orthonormal basis Π_j of the row space of the Hankel
  block at column block j, the coordinates η_j = (Π_j δ_{≥j}, N_jᵀδ_j) (N_j completing the
  first block of Π_j to a basis) satisfy δ = Gη with G block *upper bidiagonal*.

With C = BG, every term is block banded: CᵀD_iC (bandwidth ≤ 3 blocks), LC (free part causal
up to ≤ 2 blocks, constant part the same), so the LMI's pattern is a "staircase" whose chordal
cliques have at most 2–4 disturbance blocks plus the future rows of Y. Clarabel's chordal
decomposition then splits the single cone into small cones joined in a chain (rocket, T = 25,
dynamic regret: 20 s and 1.0 GB against 67 s and 2.1 GB for the same LMI in the original
coordinates; docs/regret.md). This is a lowering pass of
:class:`~balustrade.dsl.synthesis_arrow.ArrowLMI` (``lmi="banded"`` in
:mod:`.synthesis_structured`); it needs nothing of the regret problems but the block's data.

**Conditioning (issue #12).** The congruence is exact but not well conditioned when a dense
weight is whitened: cond C ≈ cond B · cond G (rocket, T = 10, W = 𝒪: 44 · 25 → 834), and the
LMI's coefficient map carries cond(C)². The optimal D block of (3.32) with W = 𝒪 has condition
55 in the original coordinates and 8.6·10⁵ in these; Clarabel then stalls (AlmostSolved 33 %
above the optimum) or ends "optimal" slightly off. No rescaling of C fixed it reliably, so
the syntheses certify every result independently and re-solve a banded result that is not ok
outside banded coordinates (:mod:`balustrade.control.regret_synthesis`; docs/regret.md). When
the problem declares the LQ form of its 𝒪 term (:mod:`balustrade.problems.regret.lifting`),
``lmi="lifted"`` lifts it instead and uses these coordinates with ``whiten=False``: no B.

:func:`banded_congruence` builds C, or returns :class:`NotBanded` with the reason when a
condition fails (a dense weight whose inverse is not banded, a Hankel rank above the block
size, a singular first block) — callers then fall back to the chordal split
(:mod:`.synthesis_structured`). :func:`banded_pieces` applies C to an arrow LMI's data.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from balustrade.dsl.synthesis_arrow import AffineMap

# Relative size below which a computed entry is taken as an exact zero of the banded structure.
ZERO_TOL = 1e-11


@dataclass(frozen=True)
class BandedCongruence:
    """cols = C η, with C = B G (B the banded factor of W⁻¹ or I, G block upper bidiagonal)."""

    C: np.ndarray
    hankel_ranks: tuple[int, ...]
    weight_inverted: bool


@dataclass(frozen=True)
class NotBanded:
    """Why the banded coordinates do not apply (the caller falls back to the chordal split)."""

    reason: str


def block_bandwidth(M: np.ndarray, p: int, tol: float = ZERO_TOL) -> int:
    """Largest |i − j| over p×p blocks (i, j) of M with an entry above tol·max|M|."""
    scale = float(np.max(np.abs(M), initial=0.0))
    if scale == 0.0:
        return 0
    nb = M.shape[0] // p
    big = np.abs(M).reshape(nb, p, -1, p).max(axis=(1, 3)) > tol * scale
    i, j = np.nonzero(big)
    return int(np.max(np.abs(i - j), initial=0))


def weight_factor(dense_terms: list[np.ndarray], p: int) -> np.ndarray | NotBanded | None:
    """B with BᵀWB = I for the one dense term W of D (None if all terms are block diagonal).

    W⁻¹ must be block tridiagonal (𝒪 and its w-block are, module docstring); B is its lower
    Cholesky factor, W⁻¹ = BBᵀ, which is block lower bidiagonal. Then BᵀB is tridiagonal,
    BᵀD_iB is banded for block-diagonal D_i, XB stays causal, and cond(B) = cond(W)^{1/2}
    (W⁻¹ itself would square the conditioning of the λ-terms).
    """
    if not dense_terms:
        return None
    W = dense_terms[0]
    for other in dense_terms[1:]:
        if not np.allclose(other, W, rtol=1e-12, atol=0.0):
            return NotBanded("more than one dense term in D")
    try:
        cho = np.linalg.cholesky(W)
    except np.linalg.LinAlgError:
        return NotBanded("the dense weight is not positive definite")
    inv_c = np.linalg.solve(cho, np.eye(W.shape[0]))
    Winv = inv_c.T @ inv_c
    if block_bandwidth(Winv, p) > 1:
        return NotBanded("the inverse of the dense weight is not block tridiagonal")
    blk = np.arange(W.shape[0]) // p
    offset = blk[:, None] - blk[None, :]
    Winv = np.where(np.abs(offset) <= 1, 0.5 * (Winv + Winv.T), 0.0)
    B = np.linalg.cholesky(Winv)
    return np.where((offset >= 0) & (offset <= 1), B, 0.0)


def free_extent(free_mask: np.ndarray, m: int, p: int) -> np.ndarray:
    """f(k) = 1 + the last column block reached by the free part in row block k (0 if none)."""
    nrb, ncb = free_mask.shape[0] // m, free_mask.shape[1] // p
    hit = free_mask.reshape(nrb, m, ncb, p).any(axis=(1, 3))
    out = np.zeros(nrb, dtype=int)
    for k in range(nrb):
        cols = np.flatnonzero(hit[k])
        out[k] = cols[-1] + 1 if cols.size else 0
    return np.maximum.accumulate(out)


def semiseparable_coordinates(L0: np.ndarray, extent: np.ndarray, m: int, p: int,
                              rtol: float = 1e-9) -> tuple[np.ndarray, tuple[int, ...]] | NotBanded:
    """G (block upper bidiagonal) with L0 G banded beyond the free extent.

    For column block j, the rows whose free part ends before j see columns ≥ j only through
    the constant L0; Π_j spans the row space of that Hankel block. η_j = (Π_jδ_{≥j}, N_jᵀδ_j).
    """
    d = L0.shape[1]
    nb = d // p
    Ginv = np.zeros((d, d))
    ranks = []
    scale = max(float(np.max(np.abs(L0), initial=0.0)), 1e-300)
    for j in range(nb):
        rows_blocks = np.flatnonzero(extent <= j)
        rows = (rows_blocks[:, None] * m + np.arange(m)[None, :]).ravel()
        H = L0[np.ix_(rows, np.arange(j * p, d))]
        r = 0
        Pi = np.zeros((0, d - j * p))
        if H.size:
            _, sv, Vt = np.linalg.svd(H, full_matrices=False)
            r = int(np.sum(sv > rtol * scale))
            Pi = Vt[:r]
        if r > p:
            return NotBanded(f"Hankel block at column block {j} has rank {r} > {p}")
        _, sv2, Vt2 = np.linalg.svd(Pi[:, :p], full_matrices=True)   # Vt2: p×p, also r = 0
        if r and sv2[r - 1] <= 1e-6 * max(sv2[0], 1e-300):
            return NotBanded(f"first block of the Hankel basis at column block {j} is singular")
        ranks.append(r)
        Ginv[j * p: j * p + r, j * p:] = Pi
        Ginv[j * p + r: (j + 1) * p, j * p: (j + 1) * p] = Vt2[r:]
    G = np.linalg.solve(Ginv, np.eye(d))
    blk = np.arange(d) // p
    offset = blk[None, :] - blk[:, None]
    in_band = (offset >= 0) & (offset <= 1)
    if np.max(np.abs(G[~in_band]), initial=0.0) > ZERO_TOL * np.max(np.abs(G)) * d:
        return NotBanded("the semiseparable coordinates are not block upper bidiagonal")
    return np.where(in_band, G, 0.0), tuple(ranks)


def banded_congruence(L0: np.ndarray, free_mask: np.ndarray, D_terms: list[np.ndarray],
                      m: int, p: int, whiten: bool = True) -> BandedCongruence | NotBanded:
    """C for the LMI above: L0 = constant part of L, free_mask = where X can be nonzero,
    D_terms = the constant matrices D_i of D = Σ α_i D_i (in the original coordinates).
    ``whiten=False``: the D_i are banded already (the lifted form of the 𝒪 weight,
    :mod:`balustrade.problems.regret.lifting`), C = G."""
    d = L0.shape[1]
    if d % p:
        return NotBanded(f"{d} columns are not whole blocks of {p}")
    dense = [Di for Di in D_terms if block_bandwidth(Di, p) > 0] if whiten else []
    B = weight_factor(dense, p)
    if isinstance(B, NotBanded):
        return B
    if B is None:
        L0B, maskB = L0, free_mask
    else:
        L0B = L0 @ B
        maskB = (free_mask.astype(float) @ (B != 0).astype(float)) > 0
    ext = free_extent(maskB, m, p)
    out = semiseparable_coordinates(L0B, ext, m, p)
    if isinstance(out, NotBanded):
        return out
    G, ranks = out
    C = G if B is None else B @ G
    return BandedCongruence(C, ranks, B is not None)


def drop_tiny(M: np.ndarray | sp.csr_matrix, tol: float = ZERO_TOL
              ) -> np.ndarray | sp.csr_matrix:
    """Entries below tol·max|M| set to exact zero (rounding noise of the banded products);
    a sparse matrix also loses them from its pattern."""
    if sp.issparse(M):
        out = M.tocsr(copy=True)
        out.data = drop_tiny(out.data, tol)
        out.eliminate_zeros()
        return out
    scale = float(np.max(np.abs(M), initial=0.0))
    return np.where(np.abs(M) > tol * scale, M, 0.0)


@dataclass(frozen=True)
class BandedPieces:
    """The arrow LMI's data in banded coordinates cols = Cη (numeric, sparse where banded)."""

    C: np.ndarray
    A: sp.csr_matrix               # vec_F(LC) = Aθ + c
    c: np.ndarray
    D: list[sp.csr_matrix]         # CᵀD_iC
    b: list[np.ndarray]            # Cᵀb_i


def banded_pieces(L: AffineMap, m: int, p: int, D_mats: Sequence[np.ndarray],
                  b_vecs: Sequence[np.ndarray] = (), whiten: bool = True
                  ) -> BandedPieces | NotBanded:
    """Transform L (rows in blocks of m, columns in blocks of p), the D_i and the b_i by the
    congruence above (``whiten``: see :func:`banded_congruence`)."""
    M, d = L.shape
    free_mask = (np.diff(L.A.indptr) > 0).reshape((M, d), order="F")
    L0 = L.c.reshape((M, d), order="F")
    cong = banded_congruence(L0, free_mask, list(D_mats), m, p, whiten)
    if isinstance(cong, NotBanded):
        return cong
    C = cong.C
    kronC = sp.kron(sp.csr_matrix(C.T), sp.identity(M, format="csr"), format="csr")
    return BandedPieces(C, drop_tiny(kronC @ L.A), drop_tiny(L0 @ C).ravel(order="F"),
                        [sp.csr_matrix(drop_tiny(C.T @ Di @ C)) for Di in D_mats],
                        [C.T @ bi for bi in b_vecs])
