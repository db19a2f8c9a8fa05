"""The last pass of the direct chain: a :class:`~balustrade.backends.passes.classify.
ClassifiedProblem` becomes the standard conic form of the solvers' own interfaces
(:class:`ConicProgram`)::

    min ½ yᵀ P y + qᵀ y   s.t.   A y + s = b,   s ∈ K = {0}ᵐ⁰ × ℝ₊ᵐ¹ × SOC × … × SOC

with ``y = (w, t)`` the OCP's decision vector and the epigraph variables of the norm/max cost
terms. ``P`` is constant (built once); ``q = q0 + Q p`` and ``b = b0 + B p + D φ(p)`` change
with the parameters ``p`` (``φ`` the non-affine parameter-only parts of quadratic rows, e.g.
``−h(x_k)`` of the CBF decrease (2.20)). ``A`` is constant too unless some affine row has
coefficients affine in ``p`` (:class:`~balustrade.backends.passes.classify.Bilinear`, e.g. the
vertex rows of (4.5c) with ``Θ_k``-vertex data as parameters): then ``A(p)`` keeps one
sparsity pattern (the union of ``A₀`` and every ``A_k``, explicit zeros kept) and only its
values change, ``A(p).data = A.data + A_param p`` (:attr:`ConicProgram.A_param`, built once),
which the solvers take as a value update of the matrix they were set up with.

Rows (``g ≤ 0`` is ``s = −g ≥ 0``): affine pieces are zero or nonnegative rows; a jointly
quadratic row without affine part is the cone ``‖L_w w + L_p p + l‖ ≤ √(−2c)`` about its
centre (the tube row (5.15b), never expanded around zero, see
:mod:`~balustrade.backends.passes.classify`); any other quadratic row ``½‖z‖² + r ≤ 0`` is the
rotated cone ``‖z‖² ≤ 2·(−r)·1`` written as the second-order cone
``((1 − r)/√2, (−1 − r)/√2, z)``. Cost terms: ℓ1 ``t_i ≥ ±a_i``, ℓ∞ ``t ≥ ±a_i``, max
``t ≥ a_i``, ℓ2 the cone ``(t, a)``, squared norms and smooth quadratics into ``P, q``.
Bounds and rows with ``|b| >= INFINITE_BOUND`` are dropped, those with ``|b| >= LARGE_BOUND``
are set aside (:attr:`ConicProgram.large`) unless ``with_large`` — the same limits as
:mod:`~balustrade.backends.passes.to_cvxpy`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca
import numpy as np
import scipy.sparse as sp

from balustrade.backends.passes.base import Pass
from balustrade.backends.passes.classify import (
    Affine,
    Bilinear,
    ClassifiedProblem,
    JointQuadratic,
    Quadratic,
    stack,
)
from balustrade.backends.passes.to_cvxpy import INFINITE_BOUND, LARGE_BOUND
from balustrade.dsl.costs import TermKind
from balustrade.dsl.ocp import BlockKind
from balustrade.errors import ConvexityError

_SQRT2 = float(np.sqrt(2.0))

#: how the multiplier of a block's rows is read from the cone duals ``z``
LINEAR, CONE_HEAD, ROTATED = "linear", "cone-head", "rotated"


@dataclass
class DualMap:
    """Rows ``rows`` of a block get ``factor · z[at]`` (``LINEAR``; ``CONE_HEAD``: the
    multiplier of ``‖v‖ ≤ r`` is the cone dual's head ``z[at[0]]``) or
    ``factor · (z[at[0]] + z[at[1]])/√2`` (``ROTATED``: the multiplier of ``½‖z‖² + r ≤ 0``)."""

    rows: np.ndarray
    at: np.ndarray
    mode: str
    factor: float = 1.0


@dataclass
class _Rows:
    """Rows of one cone in the making: ``A y + s = b0 + B p + Σ coef φ_k(p)``."""

    cone: str  # "zero", "nonneg" or "soc"
    A: sp.csr_matrix
    b0: np.ndarray
    B: sp.csr_matrix
    phi: list[tuple[int, int, float]] = field(default_factory=list)  # (row, φ index, coef)
    dual: tuple[str, np.ndarray, str, float] | None = None  # (block, rows, mode, factor)
    Ap: Bilinear | None = None  # the parameter part of A (rows affine in p · w)


@dataclass
class ConicProgram:
    """The conic data of an OCP; ``P`` upper triangular (CSC), ``A`` CSC, rows ordered
    zero, nonnegative, then the second-order cones (:attr:`cones`)."""

    n_w: int
    n_y: int
    P: sp.csc_matrix
    q0: np.ndarray
    Q: sp.csr_matrix
    A: sp.csc_matrix
    b0: np.ndarray
    B: sp.csr_matrix
    D: sp.csr_matrix
    derived: list[ca.Function]
    #: ``("zero", m0), ("nonneg", m1), ("soc", k), …`` in row order (empty groups left out)
    cones: list[tuple[str, int]]
    duals: dict[str, list[DualMap]]
    #: rows ``A w + c <= 0`` with large ``|c|`` left out (``None`` if none or ``with_large``)
    large: Affine | None
    cost_scale: float
    objective: ca.Function = field(repr=False)
    #: ``A(p).data = A.data + A_param @ p`` on the fixed pattern of ``A`` (``None``: ``A``
    #: does not depend on ``p``)
    A_param: sp.csr_matrix | None = None
    #: the rows of ``B`` with entries and ``B`` restricted to them (built on first use)
    _B_rows: tuple[np.ndarray, sp.csr_matrix] | None = field(default=None, init=False,
                                                            repr=False)

    @property
    def conic(self) -> bool:
        """Whether a second-order cone is needed (else an LP/QP)."""
        return any(kind == "soc" for kind, _ in self.cones)

    def q(self, p: np.ndarray) -> np.ndarray:
        # no nonzero in Q (e.g. the ℓ1 costs of the rendezvous): q0 itself, without a
        # sparse product of zeros (~30 µs per solve)
        return self.q0 + self.Q @ p if self.Q.nnz else self.q0.copy()

    def A_data(self, p: np.ndarray) -> np.ndarray | None:
        """The values of ``A(p)`` on the pattern of :attr:`A` (``None`` if constant)."""
        if self.A_param is None:
            return None
        return self.A.data + self.A_param @ np.asarray(p, dtype=float)

    def b(self, p: np.ndarray) -> np.ndarray:
        b = self.b0.copy()
        if self.B.nnz:
            # only the rows of B with entries (at N = 200 of the rendezvous: the 6 tube rows
            # of 7216): the same row products, without a product of zero rows
            if self._B_rows is None:
                B = sp.csr_matrix(self.B)
                rows = np.flatnonzero(np.diff(B.indptr))
                self._B_rows = (rows, B[rows])
            rows, B_rows = self._B_rows
            b[rows] += B_rows @ p
        if self.derived:
            b = b + self.D @ np.array([float(f(p)) for f in self.derived])
        return b


class ToConic(Pass):
    """ClassifiedProblem → :class:`ConicProgram` (the OCP's variables are the first ``n_w``
    entries of ``y``)."""

    name = "to-conic"

    def __init__(self, with_large: bool = False):
        self.with_large = with_large

    def accepts(self, problem: object) -> bool:
        return isinstance(problem, ClassifiedProblem)

    def apply(self, classified: ClassifiedProblem) -> tuple[ConicProgram, None]:
        return _Builder(classified, self.with_large).build(), None


def parametric_pattern(A: sp.spmatrix, Ap: Bilinear, n_p: int
                       ) -> tuple[sp.csc_matrix, sp.csr_matrix]:
    """``A(p) = A + Σ_k p_k A_k`` on one sparsity pattern: ``(A', A_param)`` with ``A'`` the
    values at ``p = 0`` on the union of the patterns of ``A`` and every ``A_k`` (canonical CSC,
    explicit zeros kept) and ``A(p).data = A'.data + A_param @ p`` (``nnz × n_p``)."""
    A = sp.coo_matrix(A)
    m, n = A.shape
    rows = np.concatenate([A.row, Ap.row]).astype(np.int64)
    cols = np.concatenate([A.col, Ap.col]).astype(np.int64)
    keys = np.unique(cols * m + rows)                       # column-major order = CSC order
    pat_cols, pat_rows = np.divmod(keys, m)
    indptr = np.concatenate([[0], np.cumsum(np.bincount(pat_cols, minlength=n))])
    data = np.zeros(keys.size)
    np.add.at(data, np.searchsorted(keys, A.col.astype(np.int64) * m + A.row), A.data)
    at = np.searchsorted(keys, Ap.col.astype(np.int64) * m + Ap.row)
    A_param = sp.csr_matrix((Ap.val, (at, Ap.par)), shape=(keys.size, n_p))
    A_param.sum_duplicates()
    out = sp.csc_matrix((data, pat_rows.astype(np.int32), indptr.astype(np.int32)),
                        shape=(m, n))
    return out, A_param


def _epigraph_size(kind: TermKind, signs: np.ndarray) -> int:
    """Epigraph variables of a norm/max term whose argument rows have the signs ``signs``
    (:func:`row_signs`): one per row of unknown sign for ℓ1 (a row of known sign is linear,
    ``|a_i| = ±a_i``), one for ℓ2, ℓ∞ and max."""
    if kind == TermKind.NORM1:
        return int(np.count_nonzero(signs == 0))
    return 1 if kind in (TermKind.NORM2, TermKind.NORMINF, TermKind.MAX) else 0


def row_signs(aff: Affine, lb: np.ndarray, ub: np.ndarray) -> np.ndarray:
    """Per row of ``A w + B p + c``: ``+1`` if it is ``>= 0`` for every ``w`` within the
    bounds ``lb <= w <= ub`` and every ``p``, ``−1`` if it is ``<= 0``, else ``0``. A row has
    a known sign when it has no parameter part and every term ``a_ij w_j`` and ``c_i`` share
    it, e.g. the slacks ``ξ >= 0`` of (2.24)/(5.15) in ``‖ξ_i‖₁``: their ℓ1 norm is then the
    linear ``Σ ξ_i`` and needs no epigraph rows (2·r·N rows and r·N variables fewer)."""
    A = sp.csr_matrix(aff.A)
    m = A.shape[0]
    var_sign = np.where(lb >= 0, 1, np.where(ub <= 0, -1, 0))
    contrib = sp.csr_matrix((np.sign(A.data) * var_sign[A.indices], A.indices, A.indptr),
                            shape=A.shape)
    nnz = np.diff(A.indptr)
    pos = np.asarray((contrib > 0).sum(axis=1)).reshape(-1)
    neg = np.asarray((contrib < 0).sum(axis=1)).reshape(-1)
    no_p = np.ones(m, bool) if aff.B is None else np.diff(sp.csr_matrix(aff.B).indptr) == 0
    c = aff.c
    signs = np.zeros(m, int)
    signs[no_p & (pos == nnz) & (c >= 0) & ((nnz > 0) | (c > 0))] = 1
    signs[no_p & (neg == nnz) & (c <= 0) & ((nnz > 0) | (c < 0))] = -1
    return signs


class _Builder:
    """Builds one :class:`ConicProgram`; holds the rows while they are made."""

    def __init__(self, classified: ClassifiedProblem, with_large: bool):
        self.c, self.with_large = classified, with_large
        self.n_w = int(classified.w.numel())
        self.n_p = int(classified.p.numel())
        lb, ub = classified.ocp.bounds()
        #: per norm/max term: the signs of its argument's rows (:func:`row_signs`)
        self.signs = {id(t): row_signs(t.form, np.asarray(lb, float), np.asarray(ub, float))
                      for t in classified.terms if isinstance(t.form, Affine)}
        self.n_y = self.n_w + sum(_epigraph_size(t.term.kind, self.signs[id(t)])
                                  for t in classified.terms if isinstance(t.form, Affine))
        self.rows: list[_Rows] = []
        self.derived: list[ca.Function] = []
        self.large_rows: list[Affine] = []
        self.cost_scale = 0.0

    # -- helpers -------------------------------------------------------------------------
    def _widen(self, A: sp.spmatrix) -> sp.csr_matrix:
        """``A`` over ``w`` as a matrix over ``y`` (zero columns for ``t``)."""
        A = sp.csr_matrix(A)
        return sp.hstack([A, sp.csr_matrix((A.shape[0], self.n_y - A.shape[1]))]).tocsr()

    def _B(self, B: sp.spmatrix | None, m: int) -> sp.csr_matrix:
        return sp.csr_matrix((m, self.n_p)) if B is None else sp.csr_matrix(B)

    def _leq(self, aff: Affine, dual=None) -> None:
        """``A w + B p + c <= 0`` as nonnegative rows ``s = −c − B p − A w``."""
        self.rows.append(_Rows("nonneg", self._widen(aff.A), -aff.c, -self._B(aff.B, aff.c.size),
                               dual=dual, Ap=aff.Ap))

    # -- build ---------------------------------------------------------------------------
    def build(self) -> ConicProgram:
        for cb in self.c.blocks:
            for pc in cb.pieces:
                self._piece(cb.block.name, cb.block.kind, pc.rows, pc.form)
        self._bounds()
        P, q0, Q = self._cost()
        order = [r for kind in ("zero", "nonneg") for r in self.rows if r.cone == kind] + \
            [r for r in self.rows if r.cone == "soc"]
        return self._assemble(order, P, q0, Q)

    def _assemble(self, order: list[_Rows], P, q0, Q) -> ConicProgram:
        cones: list[tuple[str, int]] = []
        duals: dict[str, list[DualMap]] = {cb.block.name: [] for cb in self.c.blocks}
        phi_rows, phi_cols, phi_vals = [], [], []
        offset = 0
        for r in order:
            m = r.b0.size
            if r.cone == "soc":
                cones.append(("soc", m))
            elif m:
                if cones and cones[-1][0] == r.cone:
                    cones[-1] = (r.cone, cones[-1][1] + m)
                else:
                    cones.append((r.cone, m))
            for row, k, coef in r.phi:
                phi_rows.append(offset + row)
                phi_cols.append(k)
                phi_vals.append(coef)
            if r.dual is not None:
                block, rows, mode, factor = r.dual
                at = offset + (np.arange(m) if mode == LINEAR else np.arange(2))
                duals[block].append(DualMap(rows, at, mode, factor))
            offset += m
        A = sp.vstack([r.A for r in order]).tocsc() if order else sp.csc_matrix((0, self.n_y))
        Ap = Bilinear.stack([(r.Ap, r.b0.size) for r in order]) if order else None
        A_param = None
        if Ap is not None:
            A, A_param = parametric_pattern(A, Ap, self.n_p)
        B = sp.vstack([r.B for r in order]).tocsr() if order else sp.csr_matrix((0, self.n_p))
        b0 = np.concatenate([r.b0 for r in order]) if order else np.zeros(0)
        D = sp.csr_matrix((phi_vals, (phi_rows, phi_cols)), shape=(offset, len(self.derived)))
        ocp = self.c.ocp
        return ConicProgram(self.n_w, self.n_y, P, q0, Q, A, b0.astype(float), B, D,
                            self.derived, cones, duals,
                            None if self.with_large else stack(self.large_rows),
                            self.cost_scale,
                            ca.Function("objective", [self.c.w, self.c.p], [ocp.cost.expr()]),
                            A_param)

    # -- constraints -----------------------------------------------------------------------
    def _piece(self, block: str, kind: BlockKind, rows: np.ndarray, form) -> None:
        if isinstance(form, Affine):
            self._affine_piece(block, kind, rows, form)
        elif isinstance(form, JointQuadratic):
            self._joint_quadratic(block, rows, form)
        else:
            self._quadratic_row(block, rows, form)

    def _affine_piece(self, block: str, kind: BlockKind, rows: np.ndarray, aff: Affine) -> None:
        """As :meth:`~.to_cvxpy._Builder._affine_part`: an equality is zero rows; inequality
        rows that always hold (infinite offset, or no variables and ``c <= 0``) are dropped,
        those with a large constant offset set aside."""
        if kind == BlockKind.EQ:
            self.rows.append(_Rows("zero", self._widen(aff.A), -aff.c,
                                   -self._B(aff.B, aff.c.size), dual=(block, rows, LINEAR, 1.0),
                                   Ap=aff.Ap))
            return
        no_p = ~aff.param_rows
        empty = (np.diff(aff.A.indptr) == 0) & no_p
        large = no_p & ~empty & (aff.c <= -LARGE_BOUND) & (aff.c > -INFINITE_BOUND)
        if np.any(large) and not self.with_large:
            idx = np.flatnonzero(large)
            self.large_rows.append(aff.take(idx))
        drop = (empty & (aff.c <= 0)) | (aff.c <= -INFINITE_BOUND)
        if not self.with_large:
            drop |= (aff.c <= -LARGE_BOUND) & no_p
        keep = np.flatnonzero(~drop)
        if keep.size:
            self._leq(aff.take(keep), dual=(block, rows[keep], LINEAR, 1.0))

    def _joint_quadratic(self, block: str, rows: np.ndarray, jq: JointQuadratic) -> None:
        """``½‖v‖² + aᵀw + bᵀp + c <= 0``, ``v = L_w w_I + L_p p_J + l`` about its centre:
        without affine part the cone ``(√(−2c), v)`` (multiplier: the head's ``/√(−2c)``),
        else the rotated cone with ``r = aᵀw + bᵀp + c``."""
        k = jq.Lw.shape[0]
        Lw = sp.csr_matrix((jq.Lw.ravel(), (np.repeat(np.arange(k), jq.w_index.size),
                                            np.tile(jq.w_index, k))), shape=(k, self.n_w)) \
            if k else sp.csr_matrix((0, self.n_w))
        Lp = np.zeros((k, self.n_p))
        if jq.p_index.size:
            Lp[:, jq.p_index] = jq.Lp
        if jq.linear_free and jq.c < 0:
            radius = float(np.sqrt(-2.0 * jq.c))
            A = sp.vstack([sp.csr_matrix((1, self.n_y)), -self._widen(Lw)]).tocsr()
            B = sp.csr_matrix(np.vstack([np.zeros((1, self.n_p)), Lp]))
            self.rows.append(_Rows("soc", A, np.concatenate([[radius], jq.l]), B,
                                   dual=(block, rows, CONE_HEAD, 1.0 / radius)))
            return
        r_w = sp.csr_matrix(jq.a.reshape(1, -1))
        r_p = jq.b.reshape(1, -1) if self.n_p else np.zeros((1, 0))
        self._rotated(block, rows, r_w, r_p, jq.c, None, Lw, jq.l, Lp)

    def _quadratic_row(self, block: str, rows: np.ndarray, q: Quadratic) -> None:
        """``½‖L w_I‖² + aᵀw + φ(p) <= 0`` as a rotated cone; a parameter multiplying a
        decision variable (``M ≠ 0``) would make ``A`` depend on ``p``: refused."""
        if q.M.nnz:
            raise ConvexityError(f"block {block!r}, row {int(rows[0])}: a parameter multiplies "
                                 "a decision variable in a quadratic constraint; the direct "
                                 "backend keeps the constraint matrix constant (use a CasADi "
                                 "target, e.g. target='exact')")
        k = q.L.shape[0]
        L = sp.csr_matrix((q.L.ravel(), (np.repeat(np.arange(k), q.index.size),
                                         np.tile(q.index, k))), shape=(k, self.n_w)) \
            if k else sp.csr_matrix((0, self.n_w))
        r_p = q.b.toarray().reshape(1, -1) if q.b is not None else np.zeros((1, self.n_p))
        phi = None
        if q.phi is not None:
            phi = len(self.derived)
            self.derived.append(q.phi)
        self._rotated(block, rows, sp.csr_matrix(q.a.reshape(1, -1)), r_p, q.c, phi, L,
                      np.zeros(k), np.zeros((k, self.n_p)))

    def _rotated(self, block: str, rows: np.ndarray, r_w: sp.csr_matrix, r_p: np.ndarray,
                 r_c: float, phi: int | None, Lz: sp.csr_matrix, lz: np.ndarray,
                 Lzp: np.ndarray) -> None:
        """``½‖z‖² + r <= 0`` with ``z = L_z w + L_zp p + l_z`` and ``r = r_wᵀw + r_pᵀp + r_c
        (+ φ(p))``: ``‖z‖² <= 2·(−r)·1`` is the cone ``((1 − r)/√2, (−1 − r)/√2, z)``."""
        head = self._widen(r_w) / _SQRT2  # s = b − A y: −r/√2 = −r_w w/√2 − …
        A = sp.vstack([head, head, -self._widen(Lz)]).tocsr()
        b0 = np.concatenate([[(1.0 - r_c) / _SQRT2, (-1.0 - r_c) / _SQRT2], lz])
        B = sp.csr_matrix(np.vstack([-r_p / _SQRT2, -r_p / _SQRT2, Lzp]))
        entry = _Rows("soc", A, b0, B, dual=(block, rows, ROTATED, 1.0))
        if phi is not None:
            entry.phi = [(0, phi, -1.0 / _SQRT2), (1, phi, -1.0 / _SQRT2)]
        self.rows.append(entry)

    def _bounds(self) -> None:
        """Variable bounds ``±(w_i − b_i) <= 0``; ``|b| >= INFINITE_BOUND`` dropped,
        ``|b| >= LARGE_BOUND`` set aside unless ``with_large``."""
        lb, ub = self.c.ocp.bounds()
        for sign, bound in ((-1.0, lb), (1.0, ub)):
            finite = np.abs(bound) < INFINITE_BOUND
            large = finite & (np.abs(bound) >= LARGE_BOUND)
            idx = np.flatnonzero(finite if self.with_large else finite & ~large)
            if not self.with_large and np.any(large):
                lg = np.flatnonzero(large)
                self.large_rows.append(Affine(self._select(lg, sign, self.n_w),
                                              sp.csr_matrix((lg.size, self.n_p)),
                                              -sign * bound[lg]))
            if idx.size:
                self.rows.append(_Rows("nonneg", self._select(idx, sign, self.n_y),
                                       sign * bound[idx], sp.csr_matrix((idx.size, self.n_p))))

    @staticmethod
    def _select(idx: np.ndarray, sign: float, n: int) -> sp.csr_matrix:
        return sp.csr_matrix((np.full(idx.size, sign), (np.arange(idx.size), idx)),
                             shape=(idx.size, n))

    # -- cost ------------------------------------------------------------------------------
    def _cost(self) -> tuple[sp.csc_matrix, np.ndarray, sp.csr_matrix]:
        """``(P upper triangular, q0, Q)``; the epigraph rows of norm/max terms are added to
        :attr:`rows`; records :attr:`cost_scale`, the largest cost coefficient."""
        n_y, n_w = self.n_y, self.n_w
        P = sp.csr_matrix((n_y, n_y))
        q0 = np.zeros(n_y)
        Q = sp.csr_matrix((n_y, self.n_p))
        t = n_w  # next epigraph variable
        for ct in self.c.terms:
            term, coef = ct.term, float(ct.term.coef)
            if term.kind == TermKind.SMOOTH:
                q = ct.form
                if coef < 0 and q.L.size:
                    raise ConvexityError(f"cost term {ct.label!r}: a negative weight "
                                         f"({coef:g}) on a quadratic is not convex")
                self.cost_scale = max(self.cost_scale, abs(coef) * max(
                    float(np.abs(q.a).max(initial=0.0)),
                    float((q.L ** 2).sum(axis=0).max(initial=0.0)),
                    float(np.abs(q.M.data).max(initial=0.0))))
                if q.L.size:
                    L = np.zeros((q.L.shape[0], n_y))
                    L[:, q.index] = q.L
                    Ls = sp.csr_matrix(L)
                    P = P + coef * (Ls.T @ Ls)
                q0[:n_w] += coef * q.a
                if q.M.nnz:
                    Q = Q + coef * sp.vstack([q.M, sp.csr_matrix((n_y - n_w, self.n_p))])
                continue
            if coef < 0:
                raise ConvexityError(f"cost term {ct.label!r} ({term.kind}): a negative "
                                     f"weight ({coef:g}) on a norm or max is not convex")
            aff: Affine = ct.form
            size = float(np.abs(aff.A.data).max(initial=0.0))
            self.cost_scale = max(self.cost_scale, coef * (
                size ** 2 if term.kind == TermKind.SQUARED2 else size))
            m = aff.c.size
            A = self._widen(aff.A)
            B = self._B(aff.B, m)
            if term.kind == TermKind.SQUARED2:  # coef ‖A w + B p + c‖²
                P = P + 2.0 * coef * (A.T @ A)
                q0 += 2.0 * coef * (A.T @ aff.c)
                Q = Q + 2.0 * coef * (A.T @ B)
                continue
            signs = self.signs[id(ct)]
            if term.kind == TermKind.NORM1 and np.any(signs):
                # rows of known sign: |a_i| = ±a_i is linear (the constant ±c_i is dropped:
                # the objective is evaluated on the OCP's own cost)
                known = np.flatnonzero(signs)
                q0 += coef * (A[known].T @ signs[known].astype(float))
                rest = np.flatnonzero(signs == 0)
                A, B, c = A[rest], B[rest], aff.c[rest]
                m = rest.size
                if m == 0:
                    continue
            else:
                c = aff.c
            k = m if term.kind == TermKind.NORM1 else 1
            q0[t:t + k] += coef
            T = sp.csr_matrix((np.full(m, -1.0), (np.arange(m), t + (np.arange(m) if k == m
                                                                     else np.zeros(m, int)))),
                              shape=(m, n_y))
            if term.kind == TermKind.NORM2:  # (t, a) ∈ SOC: s = (t, a) = b − A y
                head = sp.csr_matrix(([-1.0], ([0], [t])), shape=(1, n_y))
                self.rows.append(_Rows("soc", sp.vstack([head, -A]).tocsr(),
                                       np.concatenate([[0.0], c]),
                                       sp.vstack([sp.csr_matrix((1, self.n_p)), B]).tocsr()))
            else:  # ±a_i − t_i <= 0 (one side only for max and for ℓ∞ rows of known sign)
                if term.kind == TermKind.NORMINF and np.any(signs):
                    flip = np.where(signs == 0, 1.0, signs.astype(float))
                    D = sp.diags(flip)
                    self.rows.append(_Rows("nonneg", (D @ A + T).tocsr(), -flip * c,
                                           -(D @ B).tocsr()))
                    two = np.flatnonzero(signs == 0)
                    if two.size:
                        self.rows.append(_Rows("nonneg", (-A + T)[two], c[two].copy(),
                                               B[two].copy()))
                else:
                    self.rows.append(_Rows("nonneg", A + T, -c, -B))
                    if term.kind != TermKind.MAX:
                        self.rows.append(_Rows("nonneg", -A + T, c.copy(), B.copy()))
            t += k
        P = sp.triu(sp.csc_matrix(P)).tocsc()
        return P, q0, sp.csr_matrix(Q)
