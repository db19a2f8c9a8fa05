"""Structured lowering of the "arrow" LMIs of Chapter 3 to cvxpy.

Every synthesis LMI of the thesis, after the compression ``ΦᵀCΦ − 𝒪 = YᵀY`` of
:mod:`.operators`, has the shape (Schur complement form of (3.21))::

    ⎡ a   bᵀ  yᵀ ⎤
    ⎢ b   D   Lᵀ ⎥  ⪰ 0,      D = blkdiag(D_1, …, D_K),     L = [L_1 … L_K]  (M × Σd_k)
    ⎣ y   L   I_M⎦

with a scalar ``a`` (absent when x₀ is not fixed), a vector ``b`` and ``y``. When D is block
diagonal the matrix has a chordal sparsity pattern: each D_k block only meets the "separator"
rows (a, y). Taking the Schur complement with respect to D,

    [[a, yᵀ], [y, I]] − Σ_k [b_kᵀ; L_k] D_k⁻¹ [b_k, L_kᵀ] ⪰ 0,

and introducing ``Z_k ⪰ [b_kᵀ; L_k] D_k⁻¹ [b_k, L_kᵀ]`` (itself an LMI of size M+1+d_k) gives an
exact reformulation with K small cones and one separator cone instead of one large cone.
Interior-point solvers (Clarabel) form a dense block of size (cone dimension)² per PSD cone,
so this split is what makes the T = 25 problems tractable. When D = αI + βW with scalar α, β
and a dense W (competitive ratio), an orthogonal change of the disturbance coordinates
``w = Uv`` with ``W = UΛUᵀ`` makes D diagonal first; the Euclidean ball ‖w‖² ≤ ω is invariant.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cvxpy as cp
import numpy as np
import scipy.sparse as sp

from balustrade.problems.regret.banded import NotBanded, banded_congruence, drop_tiny
from balustrade.problems.regret.parametrization import Parametrization


@dataclass
class Leaf:
    """One diagonal block D_k of the arrow LMI with its coupling columns L_k (M × d_k) and b_k."""

    D: cp.Expression
    L: cp.Expression
    b: cp.Expression | None = None


def arrow_lmi(M: int, leaves: Sequence[Leaf], a: cp.Expression | None = None,
              y: cp.Expression | None = None, split: bool = True) -> list[cp.Constraint]:
    """Constraints expressing the arrow LMI above (``split`` = chordal split, else one cone)."""
    has_b = any(leaf.b is not None for leaf in leaves)
    if a is None and (y is not None or has_b):
        raise ValueError("y and b need the scalar a")
    if not split:
        return [_monolithic(M, leaves, a, y) >> 0]
    use_a_row = a is not None and has_b
    k = M + (1 if use_a_row else 0)
    cons: list[cp.Constraint] = []
    Zsum: cp.Expression | int = 0
    for leaf in leaves:
        d = leaf.D.shape[0]
        Lk = leaf.L
        if use_a_row:
            bk = leaf.b if leaf.b is not None else np.zeros(d)
            Lk = cp.vstack([cp.reshape(bk, (1, d), order="F"), Lk])
        Zk = cp.Variable((k, k), symmetric=True)
        cons.append(cp.bmat([[Zk, Lk], [Lk.T, leaf.D]]) >> 0)
        Zsum = Zsum + Zk
    if a is None:
        cons.append(np.eye(M) - Zsum >> 0)
        return cons
    yv = cp.reshape(y if y is not None else np.zeros(M), (M, 1), order="F")
    a11 = cp.reshape(a, (1, 1), order="F")
    if use_a_row:
        cons.append(cp.bmat([[a11, yv.T], [yv, np.eye(M)]]) - Zsum >> 0)
    else:
        cons.append(cp.bmat([[a11, yv.T], [yv, np.eye(M) - Zsum]]) >> 0)
    return cons


def _monolithic(M: int, leaves: Sequence[Leaf], a: cp.Expression | None,
                y: cp.Expression | None) -> cp.Expression:
    """The full arrow matrix as one cvxpy expression (the unsplit reference form)."""
    sizes = [leaf.D.shape[0] for leaf in leaves]

    def col(v: cp.Expression | None, n: int) -> cp.Expression | np.ndarray:
        return np.zeros((n, 1)) if v is None else cp.reshape(v, (n, 1), order="F")

    grid: list[list] = []
    if a is not None:
        top = [cp.reshape(a, (1, 1), order="F")]
        top += [col(leaf.b, d).T for leaf, d in zip(leaves, sizes)]
        top.append(col(y, M).T)
        grid.append(top)
    for i, leaf in enumerate(leaves):
        row = [col(leaf.b, sizes[i])] if a is not None else []
        row += [leaf.D if j == i else np.zeros((sizes[i], sizes[j])) for j in range(len(leaves))]
        row.append(leaf.L.T)
        grid.append(row)
    last = [col(y, M)] if a is not None else []
    last += [leaf.L for leaf in leaves] + [np.eye(M)]
    grid.append(last)
    return cp.bmat(grid)


def diagonal_groups(values: cp.Expression, group: int) -> list[tuple[slice, cp.Expression]]:
    """Split a vector expression of diagonal entries into groups of ``group`` diagonal blocks."""
    n = values.shape[0]
    out = []
    for start in range(0, n, group):
        sl = slice(start, min(n, start + group))
        out.append((sl, cp.diag(values[sl])))
    return out


@dataclass(frozen=True)
class BandedPieces:
    """The arrow LMI's data in banded coordinates cols = Cη (numeric, sparse where banded)."""

    C: np.ndarray
    A: sp.csr_matrix               # vec_F(LC) = Aθ + c
    c: np.ndarray
    D: list[sp.csr_matrix]         # CᵀD_iC
    b: list[np.ndarray]            # Cᵀb_i


def banded_pieces(par: Parametrization, cols: slice, D_mats: Sequence[np.ndarray],
                  b_vecs: Sequence[np.ndarray] = ()) -> BandedPieces | NotBanded:
    """Transform L = Y[:, cols], the D_i and the b_i by the congruence of :mod:`.banded`."""
    ops, M = par.ops, par.M
    d = cols.stop - cols.start
    A, c = par.Y_map(cols)
    free_mask = (np.diff(A.indptr) > 0).reshape((M, d), order="F")
    L0 = c.reshape((M, d), order="F")
    cong = banded_congruence(L0, free_mask, list(D_mats), ops.m, ops.p)
    if isinstance(cong, NotBanded):
        return cong
    C = cong.C
    kronC = sp.kron(sp.csr_matrix(C.T), sp.identity(M, format="csr"), format="csr")
    return BandedPieces(C, drop_tiny(kronC @ A), drop_tiny(L0 @ C).ravel(order="F"),
                        [sp.csr_matrix(drop_tiny(C.T @ Di @ C)) for Di in D_mats],
                        [C.T @ bi for bi in b_vecs])


def banded_lmi(par: Parametrization, cols: slice, D_terms: Sequence[tuple[object, np.ndarray]],
               a: cp.Expression | None = None,
               b_terms: Sequence[tuple[object, np.ndarray]] = (),
               y: cp.Expression | None = None) -> list[cp.Constraint] | NotBanded:
    """The arrow LMI with L = Y[:, cols], D = Σ α_iD_i, b = Σ β_ib_i in banded coordinates.

    One PSD constraint whose sparsity pattern is chordal with small cliques (:mod:`.banded`);
    it is meant for a solver that decomposes it (Clarabel's chordal decomposition). Returns
    :class:`NotBanded` when the structure is missing, so the caller can use :func:`arrow_lmi`.
    """
    M, d = par.M, cols.stop - cols.start
    pieces = banded_pieces(par, cols, [Di for _, Di in D_terms], [bi for _, bi in b_terms])
    if isinstance(pieces, NotBanded):
        return pieces
    LC = cp.reshape(pieces.A @ par.theta + pieces.c, (M, d), order="F")
    Dp = _combination([(alpha, Di) for (alpha, _), Di in zip(D_terms, pieces.D)])
    grid: list[list] = []
    if a is not None:
        bcol = (cp.reshape(_combination([(beta, bi) for (beta, _), bi in zip(b_terms, pieces.b)]),
                           (d, 1), order="F") if b_terms else np.zeros((d, 1)))
        ycol = np.zeros((M, 1)) if y is None else cp.reshape(y, (M, 1), order="F")
        grid.append([cp.reshape(a, (1, 1), order="F"), bcol.T, ycol.T])
        grid.append([bcol, Dp, LC.T])
        grid.append([ycol, LC, np.eye(M)])
    else:
        grid.append([Dp, LC.T])
        grid.append([LC, np.eye(M)])
    mat = cp.bmat(grid)
    return [0.5 * (mat + mat.T) >> 0]


def _combination(terms: Sequence[tuple[object, object]]) -> cp.Expression:
    """Σ α_i K_i for scalar expressions (or numbers) α_i and constant matrices/vectors K_i."""
    total: cp.Expression | None = None
    for alpha, K in terms:
        coef = alpha if isinstance(alpha, cp.Expression) else cp.Constant(float(alpha))
        total = coef * K if total is None else total + coef * K
    if total is None:
        raise ValueError("empty combination")
    return total
