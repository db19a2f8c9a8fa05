"""Structured synthesis problems: one vector variable θ, a few scalars, arrow LMIs, norm rows.

The regret syntheses of Chapter 3 (SPEC 2.10–2.17) share one shape. The decision variable is
a long vector θ (the causal entries of a response map) that enters every block through a
sparse affine map, plus a few scalars (γ, λ, μ, λ_i) that enter linearly. The blocks are

* an **arrow LMI** (Schur complement form of (3.21))::

      ⎡ a   bᵀ  yᵀ ⎤
      ⎢ b   D   Lᵀ ⎥ ⪰ 0,     D = Σ α_i D_i,  b = Σ β_j b_j,  L = mat(A_Lθ + c_L),  y = A_yθ + c_y
      ⎣ y   L   I  ⎦

  with scalar forms a, α_i, β_j and constant D_i, b_j (:class:`ArrowLMI`);
* **norm rows** (the SOC form of (3.41)): ``G s + Fθ + g ≤ 1`` with ``s_k ≥ ‖(A_kθ + c_k)‖``
  row by row (:class:`NormRows`).

A problem declares these blocks as data — nothing here knows a solver. How an arrow LMI
reaches the solver (banded coordinates, the chordal split or one cone) is a lowering choice
made in :mod:`balustrade.backends.synthesis_structured`; the block declares the structure
that lowering needs (the column blocks of L and the row-block size of its causal pattern).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from balustrade.errors import BalustradeError, ShapeError


# ----------------------------------------------------------------------------------------------
# scalars and their linear forms
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Scalar:
    """A linear form c·s + c₀ in the problem's scalar variables s (an affine scalar)."""

    coef: np.ndarray
    const: float = 0.0

    def _lift(self, other: object) -> Scalar:
        if isinstance(other, Scalar):
            return other
        return Scalar(np.zeros_like(self.coef), float(other))   # type: ignore[arg-type]

    def __add__(self, other: object) -> Scalar:
        o = self._lift(other)
        k = max(self.coef.size, o.coef.size)   # forms made before later scalars are shorter
        coef = np.zeros(k)
        coef[: self.coef.size] += self.coef
        coef[: o.coef.size] += o.coef
        return Scalar(coef, self.const + o.const)

    __radd__ = __add__

    def __neg__(self) -> Scalar:
        return Scalar(-self.coef, -self.const)

    def __sub__(self, other: object) -> Scalar:
        return self + (-self._lift(other))

    def __rsub__(self, other: object) -> Scalar:
        return self._lift(other) - self

    def __mul__(self, k: object) -> Scalar:
        if isinstance(k, Scalar):
            raise BalustradeError("a product of two decision scalars is not affine")
        kf = float(k)   # type: ignore[arg-type]
        return Scalar(self.coef * kf, self.const * kf)

    __rmul__ = __mul__

    def value(self, s: np.ndarray) -> float:
        return float(self.coef @ s + self.const)

    @property
    def unit_index(self) -> int | None:
        """i when the form is exactly s_i (lowerings use the variable itself), else None."""
        nz = np.flatnonzero(self.coef)
        if self.const == 0.0 and nz.size == 1 and self.coef[nz[0]] == 1.0:
            return int(nz[0])
        return None


def total(forms: Iterable[Scalar]) -> Scalar:
    """Σ of scalar forms."""
    out: Scalar | None = None
    for f in forms:
        out = f if out is None else out + f
    if out is None:
        raise BalustradeError("total: empty sum")
    return out


# ----------------------------------------------------------------------------------------------
# affine maps of θ
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class AffineMap:
    """X = mat(Aθ + c) of ``shape`` (column-major), A sparse."""

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

    def value(self, theta: np.ndarray) -> np.ndarray:
        return (self.A @ theta + self.c).reshape(self.shape, order="F")


# ----------------------------------------------------------------------------------------------
# blocks
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ArrowLMI:
    """[[a, bᵀ, yᵀ], [b, D, Lᵀ], [y, L, I]] ⪰ 0 (module docstring); ``a`` None drops the row.

    Structure for the lowering: ``col_blocks`` partition L's columns (D_i block diagonal on
    them allows the chordal split), ``block`` is the size of the disturbance blocks and
    ``row_block`` that of L's row blocks (the causal pattern the banded coordinates use).
    """

    L: AffineMap
    D: tuple[tuple[Scalar | float, np.ndarray], ...]
    col_blocks: tuple[slice, ...]
    block: int
    row_block: int
    a: Scalar | None = None
    b: tuple[tuple[Scalar | float, np.ndarray], ...] = ()
    y: AffineMap | None = None

    def __post_init__(self) -> None:
        d = self.L.shape[1]
        for _, Di in self.D:
            if Di.shape != (d, d):
                raise ShapeError("ArrowLMI D term", (d, d), Di.shape)
        for _, bi in self.b:
            if bi.shape != (d,):
                raise ShapeError("ArrowLMI b term", (d,), bi.shape)
        if self.a is None and (self.y is not None or self.b):
            raise BalustradeError("ArrowLMI: y and b need the scalar a")

    @property
    def size(self) -> int:
        """Side of the matrix as one cone."""
        return self.L.shape[0] + self.L.shape[1] + (1 if self.a is not None else 0)


@dataclass(frozen=True)
class NormRows:
    """(3.41) as data: Σ_k G[:, k]·‖row k of mat(A_kθ + c_k)‖ + fixed + Fθ + g ≤ 1.

    ``pieces`` are affine maps of shape (rows_k, p); their rows, stacked, are the norms s;
    ``G`` (sparse, rows × Σrows_k) sums them into the inequality rows.
    """

    pieces: tuple[AffineMap, ...]
    G: sp.csr_matrix
    fixed: np.ndarray
    F: sp.csr_matrix | None = None
    g: np.ndarray | None = None


@dataclass
class StructuredSDP:
    """min objective over (θ, s) subject to the blocks (module docstring); data only.

    ``objective`` is a :class:`Scalar` (linear) or, for the SH2 baseline, a list of affine maps
    whose squared Frobenius norms are summed (plus ``objective_const``).
    """

    name: str
    n_theta: int
    scalar_names: list[str] = field(default_factory=list)
    nonneg: list[bool] = field(default_factory=list)
    blocks: list[ArrowLMI | NormRows] = field(default_factory=list)
    objective: Scalar | Sequence[AffineMap] | None = None
    objective_const: float = 0.0

    # -- declarations ------------------------------------------------------------------
    def scalar(self, name: str, nonneg: bool = False) -> Scalar:
        """One new decision scalar."""
        return self.scalars(name, 1, nonneg)[0]

    def scalars(self, name: str, k: int, nonneg: bool = False) -> list[Scalar]:
        """k new decision scalars name[0..k−1]."""
        start = len(self.scalar_names)
        self.scalar_names += [name if k == 1 else f"{name}[{i}]" for i in range(k)]
        self.nonneg += [nonneg] * k
        return [Scalar(np.eye(1, start + k, start + i).ravel()) for i in range(k)]

    def add(self, block: ArrowLMI | NormRows) -> None:
        self.blocks.append(block)

    def minimize(self, objective: Scalar | Sequence[AffineMap], const: float = 0.0) -> None:
        self.objective, self.objective_const = objective, float(const)

    # -- reading a solution --------------------------------------------------------------
    @property
    def n_scalars(self) -> int:
        return len(self.scalar_names)

    def pad(self, form: Scalar | float) -> Scalar:
        """A form over all scalars declared so far (forms made earlier are shorter)."""
        if not isinstance(form, Scalar):
            return Scalar(np.zeros(self.n_scalars), float(form))
        coef = np.zeros(self.n_scalars)
        coef[: form.coef.size] = form.coef
        return Scalar(coef, form.const)

    def scalar_values(self, s: np.ndarray, name: str) -> np.ndarray:
        """The values of the scalars declared under ``name`` (a vector for name[i])."""
        idx = [i for i, nm in enumerate(self.scalar_names)
               if nm == name or nm.startswith(name + "[")]
        return np.asarray(s)[idx]
