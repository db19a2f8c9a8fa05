"""The last pass of the cvxpy chain: a :class:`~balustrade.backends.passes.classify.
ClassifiedProblem` becomes a DPP-parametrized cvxpy problem (:class:`CvxpyProgram`).

One decision vector ``W`` and one parameter vector ``P`` (the OCP's layouts); affine pieces
become ``A W + B P + c`` — with coefficients affine in the parameters (``A(p) = A₀ + Σ_k p_k
A_k``, :class:`~balustrade.backends.passes.classify.Bilinear`) the parameter part is the one
DPP product ``S (R P ∘ C W)`` (``R`` picks the parameter and weight of each nonzero of some
``A_k``, ``C`` its variable, ``S`` sums them into rows), so the problem stays parametric and
is not rebuilt when ``p`` changes — jointly quadratic rows the cone about their centre (``‖v‖ <=
√(−2c)`` for the tube row (5.15b)), quadratic rows ``½‖L W_I‖² + (a + M P)ᵀW + φ(P)`` with
a non-affine ``φ`` fed as a derived parameter (e.g. ``−h(x_k)`` of (2.20)). Bounds and
constant row offsets with ``|b| >= INFINITE_BOUND`` are left out; those with ``|b| >=
LARGE_BOUND`` are set aside (:attr:`CvxpyProgram.large`) and imposed only when a solution
violates them (:class:`~balustrade.backends.cvxpy_backend.CvxpyCompiled`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca
import cvxpy as cp
import numpy as np
import scipy.sparse as sp

from balustrade.backends.passes.base import Pass
from balustrade.backends.passes.classify import (
    Affine,
    ClassifiedProblem,
    JointQuadratic,
    Quadratic,
    stack,
)
from balustrade.dsl.costs import TermKind
from balustrade.dsl.ocp import BlockKind
from balustrade.errors import ConvexityError

#: bounds and constant row offsets at least this large in magnitude are infinite: such a
#: bound is not sent to the solver (an interior-point solver cannot hold a 1e30 row)
INFINITE_BOUND = 1e20
#: bounds (and constant row offsets) from this size on are "large but finite" (``|u| <= 1e12``
#: used as "unbounded"): they are left out of the problem sent first and only imposed, by a
#: second solve, when its solution violates them (a relaxation's minimizer that satisfies
#: the left-out rows is a minimizer of the whole problem); as rows they make PIQP and
#: Clarabel stall
LARGE_BOUND = 1e9

_ATOMS = {TermKind.SQUARED2: cp.sum_squares, TermKind.NORM1: cp.norm1,
          TermKind.NORM2: cp.norm2, TermKind.NORMINF: cp.norm_inf, TermKind.MAX: cp.max}

#: per block: (rows, constraint, factor from the constraint's dual to the rows')
Parts = list[tuple[np.ndarray, cp.Constraint, float]]


@dataclass
class CvxpyProgram:
    """The cvxpy problem and what solving it needs."""

    problem: cp.Problem
    W: cp.Variable
    P: cp.Parameter | None
    #: (CasADi function of p, cvxpy parameter) evaluated before each solve
    derived: list[tuple[ca.Function, cp.Parameter]]
    block_constraints: dict[str, Parts]
    bound_constraints: list[cp.Constraint]
    #: rows ``A w + c <= 0`` with large ``|c|`` left out of :attr:`problem`
    large: Affine | None
    conic: bool
    #: the largest cost coefficient (for rescaling a failed solve)
    cost_scale: float = 0.0
    objective: ca.Function | None = field(default=None, repr=False)

    def affine_expr(self, aff: Affine) -> cp.Expression:
        return affine_expr(aff, self.W, self.P)


def affine_expr(aff: Affine, W: cp.Variable, P: cp.Parameter | None) -> cp.Expression:
    """``A(P) W + c (+ B P)`` as a cvxpy expression (DPP: the parameter part of ``A(P)`` is
    ``S (R P ∘ C W)``, a product of a parameter-affine and a parameter-free expression)."""
    expr = aff.A @ W + aff.c
    if P is not None and aff.B.nnz:
        expr = expr + aff.B @ P
    if P is not None and aff.Ap is not None and aff.Ap.val.size:
        bl, nt = aff.Ap, aff.Ap.val.size
        t = np.arange(nt)
        R = sp.csr_matrix((bl.val, (t, bl.par)), shape=(nt, P.size))
        C = sp.csr_matrix((np.ones(nt), (t, bl.col)), shape=(nt, W.size))
        S = sp.csr_matrix((np.ones(nt), (bl.row, t)), shape=(bl.rows, nt))
        expr = expr + S @ cp.multiply(R @ P, C @ W)
    return expr


class ToCvxpy(Pass):
    """ClassifiedProblem → :class:`CvxpyProgram` (the variables are the OCP's: nothing to
    invert)."""

    name = "to-cvxpy"

    def accepts(self, problem: object) -> bool:
        return isinstance(problem, ClassifiedProblem)

    def apply(self, cp_: ClassifiedProblem) -> tuple[CvxpyProgram, None]:
        return _Builder(cp_).build(), None


class _Builder:
    """Builds one :class:`CvxpyProgram`; holds the pieces while they are made."""

    def __init__(self, classified: ClassifiedProblem):
        self.c = classified
        self.W = cp.Variable(int(classified.w.numel()), name="w")
        n_p = int(classified.p.numel())
        self.P = cp.Parameter(n_p, name="p") if n_p else None
        self.derived: list[tuple[ca.Function, cp.Parameter]] = []
        self.large_rows: list[Affine] = []
        self.cost_scale = 0.0

    def build(self) -> CvxpyProgram:
        ocp = self.c.ocp
        block_constraints: dict[str, Parts] = {}
        constraints: list[cp.Constraint] = []
        for cb in self.c.blocks:
            parts = self._block(cb.block.kind, cb.pieces)
            block_constraints[cb.block.name] = parts
            constraints += [c for _, c, _ in parts]
        bounds = self._bounds()
        objective = self._cost()
        problem = cp.Problem(cp.Minimize(objective), constraints + bounds)
        if (self.P is not None or self.derived) and not problem.is_dpp():
            raise ConvexityError(f"{ocp.name}: parameters enter the problem in a way that is not "
                                 "DPP (disciplined parametrized); check parameter products")
        return CvxpyProgram(problem, self.W, self.P, self.derived, block_constraints, bounds,
                            stack(self.large_rows), self.c.conic, self.cost_scale,
                            ca.Function("objective", [self.c.w, self.c.p], [ocp.cost.expr()]))

    # -- constraints -------------------------------------------------------------------
    def _bounds(self) -> list[cp.Constraint]:
        """Variable bounds; those with ``|bound| >= INFINITE_BOUND`` are left out, those
        with ``|bound| >= LARGE_BOUND`` are kept aside (:attr:`CvxpyProgram.large`)."""
        lb, ub = self.c.ocp.bounds()
        out = []
        finite_lb = np.flatnonzero(lb > -LARGE_BOUND)
        finite_ub = np.flatnonzero(ub < LARGE_BOUND)
        n = self.W.size
        for sign, bound in ((-1.0, lb), (1.0, ub)):
            large = np.flatnonzero((np.abs(bound) >= LARGE_BOUND)
                                   & (np.abs(bound) < INFINITE_BOUND))
            if large.size:  # sign w_i − sign b_i <= 0
                A = sp.csr_matrix((np.full(large.size, sign), (np.arange(large.size), large)),
                                  shape=(large.size, n))
                self.large_rows.append(Affine(
                    A, sp.csr_matrix((large.size, 0 if self.P is None else self.P.size)),
                    -sign * bound[large]))
        if finite_lb.size:
            out.append(self.W[finite_lb] >= lb[finite_lb])
        if finite_ub.size:
            out.append(self.W[finite_ub] <= ub[finite_ub])
        return out

    def _block(self, kind: BlockKind, pieces) -> Parts:
        parts: Parts = []
        for pc in pieces:
            if isinstance(pc.form, Affine):
                parts += self._affine_part(pc.rows, pc.form, kind)
            elif isinstance(pc.form, JointQuadratic):
                parts.append((pc.rows, *self._joint_quadratic_row(pc.form)))
            else:
                parts.append((pc.rows, self._quadratic_expr(pc.form) <= 0, 1.0))
        return parts

    def _affine_part(self, rows: np.ndarray, aff: Affine, kind: BlockKind) -> Parts:
        """``A w + B p + c (<=|==) 0`` without the rows that always hold: inequality rows
        with an infinite offset (``c <= −INFINITE_BOUND``) or no variables and ``c <= 0``."""
        if kind == BlockKind.EQ:
            return [(rows, affine_expr(aff, self.W, self.P) == 0, 1.0)]
        no_p = ~aff.param_rows
        empty = (np.diff(aff.A.indptr) == 0) & no_p
        large = np.flatnonzero(no_p & ~empty & (aff.c <= -LARGE_BOUND)
                               & (aff.c > -INFINITE_BOUND))
        if large.size:
            self.large_rows.append(aff.take(large))
        keep = np.flatnonzero(~((aff.c <= -LARGE_BOUND) & no_p | (empty & (aff.c <= 0))
                                | (aff.c <= -INFINITE_BOUND)))
        if keep.size == 0:
            return []
        if keep.size < rows.size:
            aff = aff.take(keep)
        return [(rows[keep], affine_expr(aff, self.W, self.P) <= 0, 1.0)]

    def _quadratic_expr(self, q: Quadratic) -> cp.Expression:
        value = q.a @ self.W + q.c
        if q.L.size:
            value = value + 0.5 * cp.sum_squares(q.L @ self.W[q.index])
        if self.P is not None and q.M.nnz:
            value = value + (q.M @ self.P) @ self.W
        if q.b is not None and q.b.nnz and self.P is not None:
            value = value + q.b @ self.P
        if q.phi is not None:
            derived = cp.Parameter(name=f"phi{len(self.derived)}")
            self.derived.append((q.phi, derived))
            value = value + derived
        return cp.reshape(value, (), order="F") if value.size == 1 else value

    def _joint_quadratic_row(self, jq: JointQuadratic) -> tuple[cp.Constraint, float]:
        """``½‖v‖² + aᵀw + bᵀp + c <= 0`` with ``v = L_w w + L_p p + l`` the row about its
        centre; without the affine part the cone ``‖v‖ <= √(−2c)`` (e.g. (5.15b):
        ``‖R (x_k − z_0)‖ <= 1``), whose multiplier is the row's times ``√(−2c)``."""
        v = jq.Lw @ self.W[jq.w_index] + jq.l
        if jq.p_index.size:
            v = v + jq.Lp @ self.P[jq.p_index]
        if jq.linear_free and jq.c < 0:
            radius = float(np.sqrt(-2.0 * jq.c))
            return cp.norm(v, 2) <= radius, 1.0 / radius
        value = 0.5 * cp.sum_squares(v) + jq.c
        if np.any(jq.a):
            value = value + jq.a @ self.W
        if np.any(jq.b):
            value = value + jq.b @ self.P
        return value <= 0, 1.0

    # -- cost --------------------------------------------------------------------------
    def _cost(self) -> cp.Expression:
        """The cost; records :attr:`cost_scale`, its largest coefficient."""
        total: cp.Expression | float = 0.0
        for ct in self.c.terms:
            term = ct.term
            if term.kind == TermKind.SMOOTH:
                total = total + term.coef * self._smooth_cost(ct.form, abs(term.coef))
                continue
            aff = ct.form
            atom = _ATOMS[term.kind](affine_expr(aff, self.W, self.P))
            size = float(np.abs(aff.A.data).max(initial=0.0))
            self._record_scale(abs(term.coef) * (size ** 2 if term.kind == TermKind.SQUARED2
                                                  else size))
            total = total + term.coef * atom
        return total

    def _record_scale(self, value: float) -> None:
        self.cost_scale = max(self.cost_scale, value)

    def _smooth_cost(self, q: Quadratic, coef: float) -> cp.Expression:
        """A quadratic cost term; its parameter-only part is dropped (the reported objective
        is re-evaluated from the declared cost)."""
        self._record_scale(coef * max(float(np.abs(q.a).max(initial=0.0)),
                                      float((q.L ** 2).sum(axis=0).max(initial=0.0)),
                                      float(np.abs(q.M.data).max(initial=0.0))))
        value = q.a @ self.W
        if q.L.size:
            value = value + 0.5 * cp.sum_squares(q.L @ self.W[q.index])
        if self.P is not None and q.M.nnz:
            value = value + (q.M @ self.P) @ self.W
        return value
