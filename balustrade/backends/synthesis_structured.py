"""Structured lowering of synthesis problems: arrow LMIs in banded, split or single form.

:class:`StructuredSynthesis` is :class:`~balustrade.backends.synthesis_cvxpy.CompiledSynthesis`
with one more pass: an LMI whose matrix was built by
:func:`~balustrade.dsl.synthesis_arrow.arrow_lmi` (the regret syntheses of Chapter 3) is
lowered according to the structure it declares, in the form chosen by ``lmi``; every other
block is lowered node by node as usual. The three forms of
``[[a, bᵀ, yᵀ], [b, D, Lᵀ], [y, L, I]] ⪰ 0`` (Schur complement form of (3.21)) are exact
reformulations of each other:

``"banded"`` (default)
    banded coordinates (:mod:`.lmi_banded`): one cone whose pattern is chordal with small
    cliques, left to Clarabel's chordal decomposition; when the structure is missing (a dense
    weight whose inverse is not banded, a Hankel rank above the block size) the block falls back
    to ``"split"`` and the reason is reported (``banded_fallback``).
``"lifted"``
    ``"banded"``, except that a block declaring the LQ form of its 𝒪 term (``ArrowLMI.lift``,
    :mod:`balustrade.problems.regret.lifting`) is lowered in the lifted (α, ξ) coordinates
    instead of whitening 𝒪 (``banded_route`` says which; the form is reported as
    ``"banded"``, so a result that is not ok is re-solved like a banded one). Exact, but not
    the default: measured no better than the whitened form (docs/regret.md).
``"split"``
    the chordal split: with D block diagonal on the declared column blocks, the Schur
    complement on D gives one small cone per block, ``Z_k ⪰ [b_kᵀ; L_k] D_k⁻¹ [b_k, L_kᵀ]``,
    and one separator cone ``[[a, yᵀ], [y, I]] − Σ Z_k ⪰ 0``. A D = Σ α_i c_iI + α_W W with one
    dense W is first made diagonal by the eigenvectors of W (w = Uv; the Euclidean ball is
    invariant). Anything else stays one dense cone — refused with the status ``failed`` and a
    "too large" message when Clarabel's dense KKT block of that cone would not fit in memory.
``"single"``
    the arrow matrix as one cone in the original coordinates (D made diagonal as for the
    split where it can be).

Interior-point solvers form a dense block of (cone dimension)² per PSD cone they do not
decompose: this choice is what makes the T = 25 rocket problems tractable (docs/regret.md).
The solver and its options come from a target (default preset ``"sdp"``: Clarabel with its own
tolerances); the one option this lowering adds (no chordal decomposition of an already split
problem) is set here.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cvxpy as cp
import numpy as np

from balustrade.backends import synthesis_cvxpy
from balustrade.backends.lmi_banded import NotBanded, banded_pieces
from balustrade.backends.synthesis_cvxpy import CompiledSynthesis
from balustrade.backends.synthesis_solution import SynthesisSolution
from balustrade.backends.targets import Target
from balustrade.backends.targets import target as resolve_target
from balustrade.dsl.synthesis import Constraint, Expr, SynthesisProblem
from balustrade.dsl.synthesis_arrow import AffineMap, ArrowLMI
from balustrade.errors import BalustradeError, SolverError

#: how an arrow LMI reaches the solver (module docstring)
LMI_FORMS = ("banded", "split", "single", "lifted")
#: info["banded_route"] of an arrow LMI whose 𝒪 term was lifted (no whitening of 𝒪)
LIFTED_ROUTE = "lifted: 𝒪 through its LQ definition, (x, u) coordinates, no whitening"


class StructuredSynthesis(CompiledSynthesis):
    """A synthesis problem lowered once with its arrow LMIs in the form ``lmi``.

    ``form`` is the form actually used (``"banded"``, or ``"split"``/``"single"``);
    ``banded_fallback`` says why banded coordinates did not apply (None if they did or were
    not asked for). :meth:`solve` returns a
    :class:`~balustrade.backends.synthesis_solution.SynthesisSolution` whose ``info`` records
    both and the PSD cone sizes.
    """

    def __init__(self, problem: SynthesisProblem, target: Target, lmi: str = "banded"):
        if lmi not in LMI_FORMS:
            raise BalustradeError(f"lmi: expected one of {LMI_FORMS}, got {lmi!r}")
        self.lmi = lmi
        self.form = "single" if lmi == "single" else "split"
        self.banded_fallback: str | None = None
        self.banded_route: str | None = None
        self._extra: list[cp.Constraint] = []
        self._dense: list[int] = []          # cones a solver cannot decompose (memory check)
        super().__init__(problem, target)
        if self._extra:
            self.cvxpy_problem = cp.Problem(self.cvxpy_problem.objective,
                                            self.cvxpy_problem.constraints + self._extra)
        self.psd_sizes = synthesis_cvxpy.psd_cone_sizes(self.cvxpy_problem, problem)
        if self.solver == "CLARABEL" and self.form == "split":
            # the split is already the chordal decomposition; Clarabel's own merging of the
            # cones only enlarges them again (measured 2.5x slower)
            self.options.setdefault("chordal_decomposition_enable", False)

    # -- the pass ---------------------------------------------------------------------------
    def _constraint(self, name: str, c: Constraint) -> cp.Constraint:
        struct = c.lhs.data if c.kind == ">>" else None
        if not isinstance(struct, ArrowLMI) or not _is_zero(c.rhs):
            if c.kind == ">>":
                self._dense.append(int(c.lhs.shape[0]))
            return super()._constraint(name, c)
        cons = self._arrow(struct)
        self._extra += cons[1:]
        return cons[0]

    def _arrow(self, blk: ArrowLMI) -> list[cp.Constraint]:
        self._current_theta = self.lower(blk.theta)
        a = None if blk.a is None else self.lower(blk.a)
        y = None if blk.y is None else self._vector(blk.y)
        if self.lmi in ("banded", "lifted"):
            if self.lmi == "lifted" and blk.lift is not None:
                out = _lifted(self, blk, a, y)
                if not isinstance(out, NotBanded):
                    self.form, self.banded_route = "banded", LIFTED_ROUTE
                    return out
                self.banded_route = f"lifting did not apply ({out.reason}); whitened"
            out = _banded(self, blk, a, y)
            if not isinstance(out, NotBanded):
                self.form = "banded"
                self.banded_route = self.banded_route or "banded coordinates"
                return out
            self.banded_fallback = out.reason
        leaves = _leaves(self, blk)
        if leaves is not None:
            return _arrow(blk.L.shape[0], leaves, a, y, split=self.form != "single")
        self._dense.append(blk.size)
        D = self.combination(blk.D)
        D = 0.5 * (D + D.T)
        b = self.combination(blk.b) if blk.b else None
        return _arrow(blk.L.shape[0], [_Leaf(D, self._matrix(blk.L), b)], a, y, split=False)

    # -- helpers of the pass ------------------------------------------------------------------
    def _matrix(self, m: AffineMap) -> cp.Expression:
        return cp.reshape(m.A @ self._current_theta + m.c, m.shape, order="F")

    def _vector(self, m: AffineMap) -> cp.Expression:
        return m.A @ self._current_theta + m.c

    def combination(self, terms: Sequence[tuple[Expr, object]]) -> cp.Expression:
        """Σ α_i K_i for scalar expressions α_i and constant matrices/vectors K_i."""
        out = None
        for alpha, K in terms:
            coef = self.lower(alpha)
            if not isinstance(coef, cp.Expression):
                coef = cp.Constant(float(coef))   # type: ignore[arg-type]
            piece = coef * K
            out = piece if out is None else out + piece
        if out is None:
            raise BalustradeError("empty combination")
        return out

    # -- memory -----------------------------------------------------------------------------
    def _memory_refusal(self) -> str:
        """As :class:`CompiledSynthesis`, but only for cones the solver keeps dense: the
        banded cone is decomposed by Clarabel and the split cones are small."""
        if self.solver != "CLARABEL" or not self._dense:
            return ""
        return synthesis_cvxpy.dense_cone_refusal(self.problem.name, max(self._dense))

    def solve(self, params=None) -> SynthesisSolution:   # type: ignore[override]
        sol = super().solve(params)
        sol.info.update({"lmi": self.form, "banded_fallback": self.banded_fallback,
                         "banded_route": self.banded_route})
        sol.info.setdefault("psd_cone_sizes", self.psd_sizes)
        return sol


def _is_zero(e: Expr) -> bool:
    return e.op == "constant" and not np.any(np.asarray(e.data.toarray() if hasattr(
        e.data, "toarray") else e.data))


@dataclass
class _Leaf:
    """One diagonal block D_k of the arrow LMI with its coupling columns L_k and b_k."""

    D: cp.Expression
    L: cp.Expression
    b: cp.Expression | None = None


def _is_block_diag(D: np.ndarray, blocks: Sequence[slice], tol: float = 1e-12) -> bool:
    mask = np.ones_like(D, dtype=bool)
    for sl in blocks:
        mask[sl, sl] = False
    return bool(np.max(np.abs(D[mask]), initial=0.0) <= tol * max(1.0, np.max(np.abs(D))))


def _identity_multiple(D: np.ndarray) -> float | None:
    c = float(D[0, 0])
    return c if np.allclose(D, c * np.eye(D.shape[0]), rtol=0.0, atol=1e-14) else None


def _leaves(low: StructuredSynthesis, blk: ArrowLMI) -> list[_Leaf] | None:
    """The leaves of the chordal split, or None when D has no such structure."""
    L = blk.L
    if all(_is_block_diag(Di, blk.col_blocks) for _, Di in blk.D):
        Lx = low._matrix(L)
        leaves = []
        for sl in blk.col_blocks:
            D_k = low.combination([(al, Di[sl, sl]) for al, Di in blk.D
                                   if np.any(Di[sl, sl])])
            b_k = (low.combination([(be, bi[sl]) for be, bi in blk.b]) if blk.b else None)
            leaves.append(_Leaf(D_k, Lx[:, sl], b_k))
        return leaves
    dense = [(al, Di) for al, Di in blk.D if _identity_multiple(Di) is None]
    W = dense[0][1]
    if not all(np.allclose(Di, W, rtol=1e-12, atol=0.0) for _, Di in dense):
        return None
    evals, U = np.linalg.eigh(W)
    n = evals.size
    ident = [(al, _identity_multiple(Di)) for al, Di in blk.D]
    diag = low.combination([(al, c * np.ones(n)) for al, c in ident if c is not None]
                           + [(al, evals) for al, _ in dense])
    LU = low._matrix(L.times(U))
    bU = [(be, U.T @ bi) for be, bi in blk.b]
    leaves = []
    for start in range(0, n, blk.block):
        sl = slice(start, min(n, start + blk.block))
        b_k = low.combination([(be, bi[sl]) for be, bi in bU]) if bU else None
        leaves.append(_Leaf(cp.diag(diag[sl]), LU[:, sl], b_k))
    return leaves


def _arrow(M: int, leaves: Sequence[_Leaf], a: cp.Expression | None, y: cp.Expression | None,
           split: bool) -> list[cp.Constraint]:
    """The arrow LMI over the leaves: chordal split (``split``) or one cone."""
    has_b = any(leaf.b is not None for leaf in leaves)
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


def _monolithic(M: int, leaves: Sequence[_Leaf], a: cp.Expression | None,
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


def _banded(low: StructuredSynthesis, blk: ArrowLMI, a: cp.Expression | None,
            y: cp.Expression | None) -> list[cp.Constraint] | NotBanded:
    """The arrow LMI in banded coordinates (:mod:`.lmi_banded`), one PSD constraint."""
    pieces = banded_pieces(blk.L, blk.row_block, blk.block, [Di for _, Di in blk.D],
                           [bi for _, bi in blk.b])
    if isinstance(pieces, NotBanded):
        return pieces
    return _banded_cone(low, pieces, [al for al, _ in blk.D], [be for be, _ in blk.b], a, y)


def _lifted(low: StructuredSynthesis, blk: ArrowLMI, a: cp.Expression | None,
            y: cp.Expression | None) -> list[cp.Constraint] | NotBanded:
    """The arrow LMI with its 𝒪 term through the LQ definition of 𝒪, in the coordinates
    (α, ξ) of :mod:`balustrade.problems.regret.lifting` (proof of the equivalence there):
    D' = μ𝒦 + NᵀD_rN, b' = Nᵀ(b_r + D_rn_α), a' = μk₀ + a_r + 2b_rᵀn_α + n_αᵀD_rn_α,
    y' = y + Ln_α, L' = LN — then the semiseparable coordinates of :mod:`.lmi_banded` on ξ
    (blocks of m + n), without whitening: every D' term is banded already."""
    lift = blk.lift
    N, na = np.asarray(lift.N), np.asarray(lift.n_alpha)
    rest_D = [(al, Di) for i, (al, Di) in enumerate(blk.D) if i != lift.dense]
    rest_b = [(be, bi) for j, (be, bi) in enumerate(blk.b) if j != lift.b_dense]
    D_coefs = [lift.coef] + [al for al, _ in rest_D]
    D_mats = [np.asarray(lift.K)] + [N.T @ Di @ N for _, Di in rest_D]
    b_terms = [(al, N.T @ (Di @ na)) for al, Di in rest_D] + [(be, N.T @ bi) for be, bi in rest_b]
    b_terms = [(c, v) for c, v in b_terms if np.any(v)] if a is not None else []
    pieces = banded_pieces(blk.L.times(N), blk.row_block, lift.block, D_mats,
                           [v for _, v in b_terms], whiten=False)
    if isinstance(pieces, NotBanded):
        return pieces
    if a is not None:
        a_terms = [(lift.coef, lift.k0)] + [(al, float(na @ Di @ na)) for al, Di in rest_D]
        a_terms += [(be, 2.0 * float(bi @ na)) for be, bi in rest_b]
        a = low.combination([(c, v) for c, v in a_terms if v != 0.0] or [(lift.coef, 0.0)])
        if lift.a_rest is not None:
            a = a + low.lower(lift.a_rest)
        if np.any(na):
            Ln = low._vector(blk.L.times(na.reshape(-1, 1)))
            y = Ln if y is None else y + Ln
    return _banded_cone(low, pieces, D_coefs, [c for c, _ in b_terms], a, y)


def _banded_cone(low: StructuredSynthesis, pieces, D_coefs: Sequence[Expr],
                 b_coefs: Sequence[Expr], a: cp.Expression | None, y: cp.Expression | None
                 ) -> list[cp.Constraint]:
    """[[a, bᵀ, yᵀ], [b, Σα_iD_i, LCᵀ], [y, LC, I]] ⪰ 0 from transformed pieces, one cone."""
    M, d = pieces.c.size // pieces.C.shape[1], pieces.C.shape[1]
    LC = cp.reshape(pieces.A @ low._current_theta + pieces.c, (M, d), order="F")
    Dp = low.combination(list(zip(D_coefs, pieces.D)))
    grid: list[list] = []
    if a is not None:
        bcol = (cp.reshape(low.combination(list(zip(b_coefs, pieces.b))), (d, 1), order="F")
                if b_coefs else np.zeros((d, 1)))
        ycol = np.zeros((M, 1)) if y is None else cp.reshape(y, (M, 1), order="F")
        grid.append([cp.reshape(a, (1, 1), order="F"), bcol.T, ycol.T])
        grid.append([bcol, Dp, LC.T])
        grid.append([ycol, LC, np.eye(M)])
    else:
        grid.append([Dp, LC.T])
        grid.append([LC, np.eye(M)])
    mat = cp.bmat(grid)
    return [0.5 * (mat + mat.T) >> 0]


def compile_structured(problem: SynthesisProblem, target: Target | str | None = "sdp",
                       lmi: str = "banded") -> StructuredSynthesis:
    """Lower ``problem`` once for ``target`` (default preset ``"sdp"``) with its arrow LMIs in
    the form ``lmi``; solve it with ``.solve(params)``."""
    try:
        tgt = resolve_target(target, default="sdp")
    except SolverError as exc:
        raise SolverError(f"{getattr(problem, 'name', 'synthesis')}: {exc}") from None
    return StructuredSynthesis(problem, tgt, lmi)


def solve_structured(problem: SynthesisProblem, target: Target | str | None = "sdp",
                     lmi: str = "banded") -> SynthesisSolution:
    """Compile (:func:`compile_structured`) and solve once."""
    return compile_structured(problem, target, lmi).solve()


__all__ = ["LMI_FORMS", "StructuredSynthesis", "compile_structured", "solve_structured"]
