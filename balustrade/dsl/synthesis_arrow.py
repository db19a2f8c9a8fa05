"""Arrow LMIs: a synthesis block that declares the structure a lowering may exploit.

The regret syntheses of Chapter 3 (SPEC 2.10–2.17) all have one LMI of the shape (Schur
complement form of (3.21), after the compression ΦᵀCΦ − 𝒪 = YᵀY)::

    ⎡ a   bᵀ  yᵀ ⎤
    ⎢ b   D   Lᵀ ⎥ ⪰ 0,     D = Σ α_i D_i,   b = Σ β_j b_j,   L = mat(A_Lθ + c_L),   y = A_yθ + c_y
    ⎣ y   L   I  ⎦

with scalar expressions a, α_i, β_j of the problem's variables, constant matrices D_i and
vectors b_j, and one vector variable θ entering L and y through sparse affine maps.
:func:`arrow_lmi` returns that matrix as an ordinary :func:`~balustrade.dsl.synthesis.bmat`
expression — add it with :meth:`SynthesisProblem.lmi` like any LMI, and any lowering solves
it as one cone — and attaches the structure as data (:class:`ArrowLMI`): the terms of D, the
column blocks of L, the block sizes of its causal pattern. A structured lowering
(:mod:`balustrade.backends.synthesis_structured`) reads it to choose banded coordinates or
the chordal split instead of one dense cone. The language imports no solver.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from balustrade.dsl.synthesis import Expr, as_expr, bmat, reshape
from balustrade.errors import BalustradeError, ShapeError


@dataclass(frozen=True)
class AffineMap:
    """X = mat(Aθ + c) of ``shape`` (column-major, the thesis' vec), A sparse: data only."""

    A: sp.csr_matrix
    c: np.ndarray
    shape: tuple[int, int]

    def __post_init__(self) -> None:
        rows = self.shape[0] * self.shape[1]
        if self.A.shape[0] != rows or self.c.shape != (rows,):
            raise ShapeError("AffineMap", (rows,), (self.A.shape[0], self.c.shape))

    def times(self, U: np.ndarray) -> AffineMap:
        """X U as an affine map of θ (vec(XU) = (Uᵀ ⊗ I) vec X)."""
        kronU = sp.kron(sp.csr_matrix(U.T), sp.identity(self.shape[0], format="csr"),
                        format="csr")
        return AffineMap((kronU @ self.A).tocsr(), kronU @ self.c, (self.shape[0], U.shape[1]))

    def columns(self, sl: slice) -> AffineMap:
        """X[:, sl]."""
        M = self.shape[0]
        rows = slice(sl.start * M, sl.stop * M)
        return AffineMap(self.A[rows], self.c[rows], (M, sl.stop - sl.start))

    def of(self, theta: Expr) -> Expr:
        """The expression mat(Aθ + c) of the language."""
        return reshape(self.flat(theta), self.shape)

    def flat(self, theta: Expr) -> Expr:
        """The expression Aθ + c (= vec X) of the language."""
        return as_expr(self.A) @ theta + self.c

    def value(self, theta: np.ndarray) -> np.ndarray:
        return (self.A @ theta + self.c).reshape(self.shape, order="F")


Terms = Sequence[tuple[object, np.ndarray]]


@dataclass(frozen=True)
class ArrowLMI:
    """The structure of one arrow LMI (module docstring) for a lowering to exploit.

    ``col_blocks`` partition L's columns (D_i block diagonal on them allows the chordal
    split); ``block`` is the size of the disturbance blocks and ``row_block`` that of L's row
    blocks (the causal pattern the banded coordinates use). ``a``/``alpha``/``beta`` are
    expressions of the language (numbers allowed for α, β).
    """

    theta: Expr
    L: AffineMap
    D: tuple[tuple[Expr, np.ndarray], ...]
    col_blocks: tuple[slice, ...]
    block: int
    row_block: int
    a: Expr | None = None
    b: tuple[tuple[Expr, np.ndarray], ...] = ()
    y: AffineMap | None = None
    lift: object | None = None     # a lowering's alternative form of one D term (data only)

    @property
    def size(self) -> int:
        """Side of the matrix as one cone."""
        return self.L.shape[0] + self.L.shape[1] + (1 if self.a is not None else 0)


def _combination(terms: Terms) -> Expr:
    out: Expr | None = None
    for coef, K in terms:
        piece = as_expr(coef) * as_expr(K)
        out = piece if out is None else out + piece
    if out is None:
        raise BalustradeError("arrow_lmi: D needs at least one term")
    return out


def arrow_lmi(theta: Expr, L: AffineMap, D: Terms, *, col_blocks: Sequence[slice],
              block: int, row_block: int, a: object | None = None, b: Terms = (),
              y: AffineMap | None = None, lift: object | None = None) -> Expr:
    """[[a, bᵀ, yᵀ], [b, Σα_iD_i, Lᵀ], [y, L, I]] (``a`` None drops the first row and column)
    as a :func:`bmat` expression carrying its :class:`ArrowLMI` structure in ``.data``."""
    M, d = L.shape
    D = tuple((as_expr(al), np.asarray(Di, dtype=float)) for al, Di in D)
    b = tuple((as_expr(be), np.asarray(bi, dtype=float)) for be, bi in b)
    for _, Di in D:
        if Di.shape != (d, d):
            raise ShapeError("arrow_lmi: D term", (d, d), Di.shape)
    for _, bi in b:
        if bi.shape != (d,):
            raise ShapeError("arrow_lmi: b term", (d,), bi.shape)
    if a is None and (y is not None or b):
        raise BalustradeError("arrow_lmi: y and b need the scalar a")
    Lx, Dx = L.of(theta), _combination(D)
    if a is None:
        mat = bmat([[Dx, Lx.T], [Lx, np.eye(M)]])
    else:
        bcol = (reshape(_combination(b), (d, 1)) if b else np.zeros((d, 1)))
        ycol = np.zeros((M, 1)) if y is None else y.of(theta)
        mat = bmat([[a, bcol.T, ycol.T], [bcol, Dx, Lx.T], [ycol, Lx, np.eye(M)]])
    mat.data = ArrowLMI(theta, L, D, tuple(col_blocks), int(block), int(row_block),
                        None if a is None else as_expr(a), b, y, lift)
    mat.label = "arrow LMI"
    return mat


__all__ = ["AffineMap", "ArrowLMI", "arrow_lmi"]
