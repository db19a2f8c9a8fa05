"""The classify pass: split CasADi expressions into the affine and convex-quadratic
pieces a conic (cvxpy) backend can hold.

First pass of the cvxpy chain (:mod:`balustrade.backends.passes`): :class:`Classify` turns
an OCP into a :class:`ClassifiedProblem` — every block as :class:`Piece` objects (rows and
their form), every cost term with its affine argument or quadratic decomposition — or
refuses it with an error naming the block; :mod:`~balustrade.backends.passes.to_cvxpy` then
turns the pieces into DPP-parametrized cvxpy atoms. Parameters must enter affinely; the
multiplier of a parameter-affine linear cost term is allowed (``(b + M p)ᵀ w`` is DPP), and so
are rows that are affine in the decision variables with coefficients affine in the parameters,
``A(p) w + B p + c`` with ``A(p) = A₀ + Σ_k p_k A_k`` (:class:`Bilinear`; e.g. the vertex rows
``H_X A_cl(θ^j) z_i + α_i s_j`` of (4.5c) with the vertices ``θ^j`` and the constants ``s_j``
parameters, SPEC §2.20). The structure ``A_k`` is recorded once (sparse triplets), so the
backends form ``A(p)`` on a fixed sparsity pattern per solve. Parameters may not multiply
decision variables anywhere else (a quadratic row, the cost's quadratic part).

A row that is a convex quadratic jointly in ``(w, p)`` — the tube's initial constraint
``(x_k − z_0)ᵀ P (x_k − z_0) <= 1`` ((2.15), (5.15b)) with the state ``x_k`` a parameter —
is kept about its centre (:func:`joint_quadratic`): ``½‖L_w w + L_p p + l‖² + affine``.
Expanding it around zero instead (``‖L z_0‖² − 2 (P x_k)ᵀ z_0 + x_kᵀ P x_k <= 1``) makes
the solver cancel constants of size ``|x_k|²‖P‖`` (1.4·10⁵ on the rendezvous), which it
cannot do to its tolerances.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np
import scipy.sparse as sp

from balustrade.backends.passes.base import Pass
from balustrade.dsl.costs import Term, TermKind
from balustrade.dsl.ocp import OCP, Block, BlockKind
from balustrade.errors import ConvexityError


@dataclass
class Bilinear:
    """The parameter-dependent part of a constraint matrix, ``Σ_k p_k A_k``, as triplets: entry
    ``(row[t], col[t])`` of ``A(p)`` gains ``val[t] · p[par[t]]`` (one triplet per nonzero of
    some ``A_k``; ``rows`` the number of rows)."""

    row: np.ndarray
    col: np.ndarray
    par: np.ndarray
    val: np.ndarray
    rows: int

    def take(self, keep: np.ndarray) -> Bilinear:
        """The rows ``keep`` (in that order), renumbered ``0 … len(keep) − 1``."""
        keep = np.asarray(keep, dtype=int)
        new = np.full(self.rows, -1, dtype=int)
        new[keep] = np.arange(keep.size)
        sel = new[self.row] >= 0
        return Bilinear(new[self.row[sel]], self.col[sel], self.par[sel], self.val[sel],
                        int(keep.size))

    def matrix(self, p: np.ndarray, n_cols: int) -> sp.csr_matrix:
        """``Σ_k p_k A_k`` at ``p`` (``rows × n_cols``)."""
        return sp.csr_matrix((self.val * np.asarray(p, float)[self.par], (self.row, self.col)),
                             shape=(self.rows, n_cols))

    @property
    def param_rows(self) -> np.ndarray:
        """Per row: whether some entry of it depends on a parameter."""
        out = np.zeros(self.rows, dtype=bool)
        out[self.row] = True
        return out

    @staticmethod
    def stack(parts: list[tuple[Bilinear | None, int]]) -> Bilinear | None:
        """Blocks of ``m`` rows each (``None``: no parameter part) one below the other."""
        if all(b is None for b, _ in parts):
            return None
        rows, cols, pars, vals, offset = [], [], [], [], 0
        for b, m in parts:
            if b is not None:
                rows.append(b.row + offset)
                cols.append(b.col)
                pars.append(b.par)
                vals.append(b.val)
            offset += m
        return Bilinear(np.concatenate(rows), np.concatenate(cols), np.concatenate(pars),
                        np.concatenate(vals), offset)


@dataclass
class Affine:
    """``A(p) w + B p + c`` (sparse ``A``, ``B``) with ``A(p) = A + Σ_k p_k A_k`` when ``Ap``
    holds the parameter part (:class:`Bilinear`; only for constraint rows), else ``A``."""

    A: sp.csr_matrix
    B: sp.csr_matrix
    c: np.ndarray
    Ap: Bilinear | None = None

    def take(self, keep: np.ndarray) -> Affine:
        """The rows ``keep``."""
        return Affine(self.A[keep], self.B[keep], self.c[keep],
                      None if self.Ap is None else self.Ap.take(keep))

    @property
    def param_rows(self) -> np.ndarray:
        """Per row: whether it depends on a parameter (through ``B`` or ``A(p)``)."""
        dep = np.diff(sp.csr_matrix(self.B).indptr) != 0
        return dep | self.Ap.param_rows if self.Ap is not None else dep


@dataclass
class Quadratic:
    """``½ ‖L w_I‖² + (a + M p)ᵀ w + φ(p)``: convex quadratic in ``w`` (``LᵀL = H ⪰ 0`` on
    the indices ``I``), with a parameter-affine linear coefficient (DPP: ``(M p)ᵀ w``) and
    a parameter-only part ``φ(p) = expr(0, p)``. ``φ`` is affine (``b p + c``) or, when it
    is not, a CasADi function evaluated before each solve and fed to cvxpy as a derived
    parameter (e.g. ``−h(x)`` in the CBF decrease (2.20) with the state ``x`` a parameter).
    """

    index: np.ndarray
    L: np.ndarray
    a: np.ndarray
    M: sp.csr_matrix
    b: sp.csr_matrix | None
    c: float
    phi: ca.Function | None


def _dm_to_sparse(m: ca.DM) -> sp.csr_matrix:
    m = ca.DM(m)
    if m.nnz() == 0:
        return sp.csr_matrix(m.shape)
    col, row = m.sparsity().get_ccs()
    return sp.csc_matrix((np.asarray(m.nonzeros(), dtype=float), row, col),
                         shape=m.shape).tocsr()


def _constant(expr: ca.SX, w: ca.SX, p: ca.SX) -> bool:
    return not (ca.depends_on(expr, w) or ca.depends_on(expr, p)) if expr.nnz() else True


def _evaluate(expr: ca.SX, w: ca.SX, p: ca.SX) -> ca.DM:
    f = ca.Function("f", [w, p], [expr])
    return f(np.zeros(w.numel()), np.zeros(p.numel()))


def _vector(m: ca.DM) -> np.ndarray:
    """A (sparse) CasADi column as a dense float vector, through its nonzeros: converting a
    DM with ``np.asarray`` goes element by element (seconds for the ~5000-entry gradients of
    the rendezvous at N = 200)."""
    return _dm_to_sparse(m).toarray().reshape(-1)


def _hessian_support(Hz: ca.SX, w: ca.SX, p: ca.SX, symmetrize: bool = False
                     ) -> tuple[np.ndarray, np.ndarray]:
    """The indices where the constant Hessian ``Hz`` has nonzero columns and the dense
    Hessian on them, built from the sparse value (never densifying the whole ``n × n``
    matrix: 23·10⁶ entries for one tube row of the rendezvous at N = 200)."""
    H = _dm_to_sparse(_evaluate(Hz, w, p)).tocsc()
    if symmetrize:
        H = (0.5 * (H + H.T)).tocsc()
    H.eliminate_zeros()
    support = np.flatnonzero(np.diff(H.indptr))
    return support, H[support][:, support].toarray()


def affine(expr: ca.SX, w: ca.SX, p: ca.SX, block: str, bilinear: bool = False
           ) -> Affine | None:
    """Return the affine decomposition of ``expr`` or ``None`` if it is not affine. With
    ``bilinear`` also ``A(p) w + B p + c`` with ``A(p)`` affine in ``p`` (:class:`Bilinear`:
    the Jacobian in ``w`` does not depend on ``w`` and its nonzeros are affine in ``p``)."""
    Jw = ca.jacobian(expr, w)
    Jp = ca.jacobian(expr, p) if p.numel() else ca.SX(expr.numel(), 0)
    if _constant(Jw, w, p) and _constant(Jp, w, p):
        c = _vector(_evaluate(expr, w, p))
        return Affine(_dm_to_sparse(_evaluate(Jw, w, p)), _dm_to_sparse(_evaluate(Jp, w, p)),
                      c)
    if not bilinear or not p.numel() or ca.depends_on(Jw, w):
        return None
    return _bilinear(expr, Jw, Jp, w, p)


def _bilinear(expr: ca.SX, Jw: ca.SX, Jp: ca.SX, w: ca.SX, p: ca.SX) -> Affine | None:
    """``A(p) w + B p + c`` for ``expr`` affine in ``w`` with ``Jw = A(p)``: ``A₀ = A(0)``,
    ``A_k`` from the (constant) Jacobian of the nonzeros of ``A(p)`` in ``p``, ``B`` the
    ``p``-Jacobian at ``w = 0`` (must be constant: ``expr`` affine in ``p`` for fixed ``w``);
    ``None`` if any of it fails."""
    nz = Jw.nz[:] if Jw.nnz() else ca.SX(0, 1)
    T = ca.jacobian(nz, p)
    Jp0 = ca.substitute(Jp, w, ca.DM.zeros(w.numel()))
    if not (_constant(T, w, p) and _constant(Jp0, w, p)):
        return None
    rows, cols = Jw.sparsity().get_triplet()
    Tm = _dm_to_sparse(_evaluate(T, w, p)).tocoo()
    keep = Tm.data != 0
    rows, cols = np.asarray(rows, int), np.asarray(cols, int)
    Ap = Bilinear(rows[Tm.row[keep]], cols[Tm.row[keep]], Tm.col[keep].astype(int),
                  Tm.data[keep].astype(float), int(expr.numel()))
    c = _vector(_evaluate(expr, w, p))
    return Affine(_dm_to_sparse(_evaluate(Jw, w, p)), _dm_to_sparse(_evaluate(Jp0, w, p)), c,
                  Ap)


def quadratic(expr: ca.SX, w: ca.SX, p: ca.SX, where: str) -> Quadratic:
    """Decompose a scalar that is a convex quadratic of the decision variables ``w`` whose
    gradient is affine in the parameters ``p``; refuse anything else naming ``where``."""
    grad_w = ca.gradient(expr, w)
    Hw = ca.jacobian(grad_w, w)
    M = ca.jacobian(grad_w, p) if p.numel() else ca.SX(w.numel(), 0)
    if not (_constant(Hw, w, p) and _constant(M, w, p)):
        raise ConvexityError(
            f"{where}: the expression is neither affine nor a convex quadratic of the decision "
            "variables (with parameters entering the linear part affinely); the convex "
            "backends (cvxpy, direct) cannot hold it (use a CasADi target, e.g. target='exact')")
    index, Hs = _hessian_support(Hw, w, p)
    _require_psd(Hs, where)
    a = _vector(_evaluate(grad_w, w, p))
    phi_expr = ca.substitute(expr, w, ca.DM.zeros(w.numel()))
    phi_aff = affine(phi_expr, w, p, where)
    if phi_aff is not None:
        b, c, phi = phi_aff.B, float(phi_aff.c[0]), None
    else:
        b, c, phi = None, 0.0, ca.Function("phi", [p], [phi_expr])
    return Quadratic(index, psd_factor(Hs), a, _dm_to_sparse(_evaluate(M, w, p)), b, c, phi)


@dataclass
class JointQuadratic:
    """``½ ‖L_w w_I + L_p p_J + l‖² + aᵀ w + bᵀ p + c``: a row that is a convex quadratic
    jointly in the decision variables and the parameters (constant joint Hessian
    ``[L_w L_p]ᵀ[L_w L_p] ⪰ 0`` on the indices ``I``, ``J``), written about its centre.
    ``a``, ``b`` hold only the gradient outside the range of the Hessian (often zero), so
    that ``c`` is the row's value at the centre (``−1`` for an ellipsoid ``(x−z)ᵀP(x−z) − 1``).
    """

    w_index: np.ndarray
    p_index: np.ndarray
    Lw: np.ndarray
    Lp: np.ndarray
    l: np.ndarray
    a: np.ndarray
    b: np.ndarray
    c: float

    @property
    def linear_free(self) -> bool:
        """No affine part: the row is ``½‖·‖² + c <= 0``, i.e. the cone ``‖·‖ <= √(−2c)``."""
        return not (np.any(self.a) or np.any(self.b))


def joint_quadratic(expr: ca.SX, w: ca.SX, p: ca.SX) -> JointQuadratic | None:
    """Decompose a scalar row that is quadratic jointly in ``(w, p)`` with a positive
    semidefinite joint Hessian ``H`` as ``½‖L z + l‖² + gᵣᵀ z + c'`` (``z = (w, p)``,
    ``LᵀL = H``, ``Lᵀl`` the part of the gradient at zero ``g`` in the range of ``H``,
    ``gᵣ = g − Lᵀl``, ``c' = expr(0) − ½‖l‖²``); ``None`` if it is not (its Hessian depends on
    ``(w, p)``, e.g. a nonlinear ``−h(x_k)``, or is indefinite, e.g. ``−x_kᵀ P x_k``)."""
    z = ca.vertcat(w, p)
    grad = ca.gradient(expr, z)
    Hz = ca.jacobian(grad, z)
    if not _constant(Hz, w, p):
        return None
    support, Hs = _hessian_support(Hz, w, p, symmetrize=True)
    if _negative_eigenvalue(Hs) is not None:
        return None
    L = psd_factor(Hs)
    g = _vector(_evaluate(grad, w, p))
    c = float(_vector(_evaluate(expr, w, p))[0])
    # L has orthogonal rows (eigen-factor): Lᵀl = projection of g onto range(H)
    row_norms2 = np.einsum("ij,ij->i", L, L)
    l = (L @ g[support]) / row_norms2 if L.size else np.zeros(0)
    g_rest = g.copy()
    g_rest[support] -= L.T @ l
    g_rest[np.abs(g_rest) <= 1e-12 * max(1.0, float(np.abs(g).max(initial=0.0)))] = 0.0
    nw = int(w.numel())
    in_w = support < nw
    return JointQuadratic(support[in_w], support[~in_w] - nw, L[:, in_w], L[:, ~in_w], l,
                          g_rest[:nw], g_rest[nw:], c - 0.5 * float(l @ l))


def _negative_eigenvalue(H: np.ndarray) -> float | None:
    """The smallest eigenvalue of ``H`` if it is negative beyond rounding (``H`` is not
    positive semidefinite), else ``None``."""
    if H.size == 0:
        return None
    lam = np.linalg.eigvalsh(0.5 * (H + H.T))
    return float(lam.min()) if lam.min() < -1e-9 * max(1.0, float(np.abs(lam).max())) \
        else None


def _require_psd(H: np.ndarray, where: str) -> None:
    lam_min = _negative_eigenvalue(H)
    if lam_min is not None:
        raise ConvexityError(f"{where}: the Hessian has a negative eigenvalue "
                             f"({lam_min:.3g}); a nonconvex block cannot be sent to the "
                             "convex backends (cvxpy, direct) "
                             "(use a CasADi target, e.g. target='exact')")


def psd_factor(H: np.ndarray) -> np.ndarray:
    """``L`` with ``LᵀL = H`` for ``H ⪰ 0`` and orthogonal rows; drops null directions.

    A diagonal ``H`` is factored exactly (``√H_ii``); otherwise by eigenvalues, dropping only
    those at the level of the eigen-solver's rounding (``8 n ε max λ``): a cost
    ``10¹² u₀² + u₁²`` must keep its ``u₁²``.
    """
    H = 0.5 * (H + H.T)
    n = H.shape[0]
    if n and not np.any(H - np.diag(np.diagonal(H))):
        d = np.diagonal(H)
        keep = np.flatnonzero(d > 0)
        L = np.zeros((keep.size, n))
        L[np.arange(keep.size), keep] = np.sqrt(d[keep])
        return L
    lam, V = np.linalg.eigh(H)
    keep = lam > 8 * max(n, 1) * np.finfo(float).eps * max(float(lam.max(initial=0.0)), 1e-300)
    return (V[:, keep] * np.sqrt(lam[keep])).T


# -- the pass ----------------------------------------------------------------------------
@dataclass(frozen=True)
class Piece:
    """Rows ``rows`` of a block in one form: :class:`Affine` (all of them, ``(<=|==) 0``),
    :class:`JointQuadratic` (one row, kept about its centre) or :class:`Quadratic` (one
    row, expanded in the decision variables)."""

    rows: np.ndarray
    form: Affine | JointQuadratic | Quadratic


@dataclass(frozen=True)
class ClassifiedBlock:
    """A block and its pieces, in the order the lowering emits them: the non-affine rows
    one by one, then the affine rows stacked (a wholly affine block is one piece)."""

    block: Block
    pieces: tuple[Piece, ...]

    @property
    def conic(self) -> bool:
        """Whether some row is not affine (needs a cone or a quadratic row)."""
        return any(not isinstance(pc.form, Affine) for pc in self.pieces)


@dataclass(frozen=True)
class ClassifiedTerm:
    """A cost term with its label and form: a :class:`Quadratic` (smooth terms) or the
    :class:`Affine` argument of a norm, max or squared norm."""

    term: Term
    label: str
    form: Affine | Quadratic


@dataclass(frozen=True)
class ClassifiedProblem:
    """An OCP whose blocks and cost terms are classified (symbols ``w``, ``p`` stacked as
    the OCP's layouts)."""

    ocp: OCP
    w: ca.SX
    p: ca.SX
    blocks: tuple[ClassifiedBlock, ...]
    terms: tuple[ClassifiedTerm, ...]

    @property
    def conic(self) -> bool:
        """Whether a second-order cone (or a quadratic row) is needed."""
        return any(b.conic for b in self.blocks) or any(
            t.term.kind == TermKind.NORM2 for t in self.terms)


def classify_block(block: Block, w: ca.SX, p: ca.SX) -> ClassifiedBlock:
    """The pieces of ``block`` (:class:`ClassifiedBlock`); a nonlinear equality or a row that
    is neither affine nor convex quadratic raises :class:`ConvexityError` naming it."""
    aff = affine(block.expr, w, p, block.name, bilinear=True)
    if aff is not None:
        return ClassifiedBlock(block, (Piece(np.arange(block.rows), aff),))
    if block.kind == BlockKind.EQ:
        raise ConvexityError(f"block {block.name!r} ({block.tag}, {block.rows} rows): an "
                             "equality constraint must be affine for the convex backends "
                             "(cvxpy, direct); this one is nonlinear (use a CasADi target, e.g. "
                             "target='exact')")
    pieces, affine_rows, affine_parts = [], [], []
    for r in range(block.rows):
        row_expr = block.expr[r]
        row_aff = affine(row_expr, w, p, block.name, bilinear=True)
        if row_aff is not None:
            affine_rows.append(r)
            affine_parts.append(row_aff)
            continue
        jq = joint_quadratic(row_expr, w, p)
        form = jq if jq is not None and jq.w_index.size else \
            quadratic(row_expr, w, p, f"block {block.name!r}, row {r}")
        pieces.append(Piece(np.array([r]), form))
    if affine_rows:
        pieces.append(Piece(np.array(affine_rows), stack(affine_parts)))
    return ClassifiedBlock(block, tuple(pieces))


def classify_term(k: int, term: Term, w: ca.SX, p: ca.SX) -> ClassifiedTerm:
    """A smooth term as a :class:`Quadratic`, any other as the :class:`Affine` decomposition
    of its argument; else :class:`ConvexityError` naming the term."""
    label = term.label or f"{term.kind}#{k}"
    if term.kind == TermKind.SMOOTH:
        return ClassifiedTerm(term, label, quadratic(term.expr, w, p, f"cost term {label!r}"))
    aff = affine(term.expr, w, p, label)
    if aff is None:
        raise ConvexityError(f"cost term {label!r} ({term.kind}): its argument must be "
                             "affine in the decision variables for the convex backends "
                             "(cvxpy, direct)")
    return ClassifiedTerm(term, label, aff)


def stack(parts: list[Affine]) -> Affine | None:
    """The rows of ``parts`` as one :class:`Affine` (``None`` for no parts)."""
    if not parts:
        return None
    return Affine(sp.vstack([a.A for a in parts]).tocsr(),
                  sp.vstack([a.B for a in parts]).tocsr(),
                  np.concatenate([a.c for a in parts]),
                  Bilinear.stack([(a.Ap, a.c.size) for a in parts]))


class Classify(Pass):
    """OCP → :class:`ClassifiedProblem` (nothing to invert: the variables are the OCP's)."""

    name = "classify"

    def accepts(self, problem: object) -> bool:
        return isinstance(problem, OCP)

    def apply(self, ocp: OCP) -> tuple[ClassifiedProblem, None]:
        w, p = ocp.decision_vector(), ocp.parameter_vector()
        blocks = tuple(classify_block(b, w, p) for b in ocp.blocks)
        terms = tuple(classify_term(k, t, w, p) for k, t in enumerate(ocp.cost.terms))
        return ClassifiedProblem(ocp, w, p, blocks, terms), None
