"""Lowering of a :class:`~balustrade.dsl.structured_sdp.StructuredSDP` to cvxpy, and its solve.

The arrow LMI ``[[a, bᵀ, yᵀ], [b, D, Lᵀ], [y, L, I]] ⪰ 0`` of the regret syntheses (Schur
complement form of (3.21)) reaches the solver in one of three exact forms, chosen by ``lmi``:

``"banded"`` (default)
    banded coordinates (:mod:`.lmi_banded`): one cone whose pattern is chordal with small
    cliques, left to Clarabel's chordal decomposition; when the structure is missing (a dense
    weight whose inverse is not banded, a Hankel rank above the block size) the block falls back
    to ``"split"`` and the reason is reported.
``"split"``
    the chordal split: with D block diagonal on the declared column blocks, the Schur
    complement on D gives one small cone per block, ``Z_k ⪰ [b_kᵀ; L_k] D_k⁻¹ [b_k, L_kᵀ]``,
    and one separator cone ``[[a, yᵀ], [y, I]] − Σ Z_k ⪰ 0``. A D = Σ α_i I + α_W W with one
    dense W is first made diagonal by the eigenvectors of W (w = Uv; the Euclidean ball is
    invariant). Anything else stays one dense cone — refused with the status ``too_large``
    when Clarabel's dense KKT block of that cone would not fit in memory.
``"single"``
    the arrow matrix as one cone in the original coordinates.

Interior-point solvers form a dense block of (cone dimension)² per PSD cone: this choice is
what makes the T = 25 rocket problems tractable (docs/regret.md). Norm rows (3.41) become one
vectorized second-order cone. The solver and its options come from a target
(:mod:`.targets`, default ``"clarabel"``); solver-specific defaults live here.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import cvxpy as cp
import numpy as np

from balustrade.backends.lmi_banded import NotBanded, banded_pieces
from balustrade.backends.targets import Target
from balustrade.backends.targets import target as resolve_target
from balustrade.dsl.structured_sdp import AffineMap, ArrowLMI, NormRows, Scalar, StructuredSDP
from balustrade.errors import BalustradeError

LMI_FORMS = ("banded", "split", "single")
OK_STATUSES = ("optimal", "optimal_inaccurate")

# Clarabel keeps a dense block of (svec size)² per PSD cone in its KKT system; the measured
# peak resident memory was ≈ 7 such blocks (22.8 GB for the 203-cone of SCRW at T = 25).
_CLARABEL_DENSE_CONE_FACTOR = 7 * 8


@dataclass
class StructuredSolution:
    """What one solve returned: status, values of θ and the scalars, and how it was lowered."""

    status: str
    theta: np.ndarray | None = None
    scalars: np.ndarray | None = None
    objective: float | None = None
    solve_time: float = 0.0
    info: dict = field(default_factory=dict)

    @property
    def has_values(self) -> bool:
        return self.status in OK_STATUSES and self.theta is not None


# ----------------------------------------------------------------------------------------------
# the arrow LMI in its three forms
# ----------------------------------------------------------------------------------------------
@dataclass
class _Leaf:
    """One diagonal block D_k of the arrow LMI with its coupling columns L_k and b_k."""

    D: cp.Expression
    L: cp.Expression
    b: cp.Expression | None = None


class _Lowering:
    """cvxpy variables of one problem and the conversion of its forms and maps."""

    def __init__(self, sdp: StructuredSDP):
        self.sdp = sdp
        self.theta = cp.Variable(sdp.n_theta, name="theta")
        self.s = cp.Variable(sdp.n_scalars, name="scalars") if sdp.n_scalars else None

    def scalar(self, form: Scalar | float) -> cp.Expression:
        if not isinstance(form, Scalar):
            return cp.Constant(float(form))
        i = form.unit_index
        if i is not None:
            return self.s[i]
        k = form.coef.size
        return self.s[:k] @ form.coef + form.const

    def matrix(self, m: AffineMap) -> cp.Expression:
        return cp.reshape(m.A @ self.theta + m.c, m.shape, order="F")

    def vector(self, m: AffineMap) -> cp.Expression:
        return m.A @ self.theta + m.c

    def combination(self, terms: Sequence[tuple[Scalar | float, object]]) -> cp.Expression:
        """Σ α_i K_i for scalar forms (or numbers) α_i and constant matrices/vectors K_i."""
        out: cp.Expression | None = None
        for alpha, K in terms:
            piece = self.scalar(alpha) * K
            out = piece if out is None else out + piece
        if out is None:
            raise BalustradeError("empty combination")
        return out


def _is_block_diag(D: np.ndarray, blocks: Sequence[slice], tol: float = 1e-12) -> bool:
    mask = np.ones_like(D, dtype=bool)
    for sl in blocks:
        mask[sl, sl] = False
    return bool(np.max(np.abs(D[mask]), initial=0.0) <= tol * max(1.0, np.max(np.abs(D))))


def _identity_multiple(D: np.ndarray) -> float | None:
    c = float(D[0, 0])
    return c if np.allclose(D, c * np.eye(D.shape[0]), rtol=0.0, atol=1e-14) else None


def _leaves(low: _Lowering, blk: ArrowLMI) -> list[_Leaf] | None:
    """The leaves of the chordal split, or None when D has no such structure."""
    L = blk.L
    if all(_is_block_diag(Di, blk.col_blocks) for _, Di in blk.D):
        Lx = low.matrix(L)
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
    LU = low.matrix(L.times(U))
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


def _banded(low: _Lowering, blk: ArrowLMI, a: cp.Expression | None, y: cp.Expression | None
            ) -> list[cp.Constraint] | NotBanded:
    """The arrow LMI in banded coordinates (:mod:`.lmi_banded`), one PSD constraint."""
    M, d = blk.L.shape
    pieces = banded_pieces(blk.L, blk.row_block, blk.block, [Di for _, Di in blk.D],
                           [bi for _, bi in blk.b])
    if isinstance(pieces, NotBanded):
        return pieces
    LC = cp.reshape(pieces.A @ low.theta + pieces.c, (M, d), order="F")
    Dp = low.combination([(al, Di) for (al, _), Di in zip(blk.D, pieces.D)])
    grid: list[list] = []
    if a is not None:
        bcol = (cp.reshape(low.combination([(be, bi) for (be, _), bi in zip(blk.b, pieces.b)]),
                           (d, 1), order="F") if blk.b else np.zeros((d, 1)))
        ycol = np.zeros((M, 1)) if y is None else cp.reshape(y, (M, 1), order="F")
        grid.append([cp.reshape(a, (1, 1), order="F"), bcol.T, ycol.T])
        grid.append([bcol, Dp, LC.T])
        grid.append([ycol, LC, np.eye(M)])
    else:
        grid.append([Dp, LC.T])
        grid.append([LC, np.eye(M)])
    mat = cp.bmat(grid)
    return [0.5 * (mat + mat.T) >> 0]


# ----------------------------------------------------------------------------------------------
# norm rows (3.41)
# ----------------------------------------------------------------------------------------------
def _norm_rows(low: _Lowering, blk: NormRows) -> list[cp.Constraint]:
    lhs: cp.Expression = cp.Constant(blk.fixed)
    cons: list[cp.Constraint] = []
    if blk.pieces:
        npairs = sum(piece.shape[0] for piece in blk.pieces)
        s = cp.Variable(npairs, nonneg=True)
        cons.append(cp.SOC(s, cp.vstack([low.matrix(piece) for piece in blk.pieces]), axis=1))
        lhs = lhs + blk.G @ s
    if blk.F is not None:
        lhs = lhs + blk.F @ low.theta
    if blk.g is not None:
        lhs = lhs + blk.g
    return cons + [lhs <= 1]


# ----------------------------------------------------------------------------------------------
# memory refusal of a dense cone
# ----------------------------------------------------------------------------------------------
def _mem_available_bytes() -> float:
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable"):
                    return int(line.split()[1]) * 1024.0
    except OSError:
        pass
    return float("inf")


def _dense_cone_refusal(name: str, size: int, solver: str) -> str | None:
    """A message instead of an out-of-memory kill: a dense PSD cone too large for Clarabel."""
    if solver != "CLARABEL":
        return None
    svec = size * (size + 1) // 2
    need = _CLARABEL_DENSE_CONE_FACTOR * float(svec) ** 2
    avail = _mem_available_bytes()
    if need <= 0.8 * avail:
        return None
    return (f"{name}: one dense PSD cone of size {size} needs about {need / 2**30:.1f} GB "
            f"with Clarabel, {avail / 2**30:.1f} GB available; use solver='SCS' (it only "
            "needs eigendecompositions of the cone)")


# ----------------------------------------------------------------------------------------------
# solve
# ----------------------------------------------------------------------------------------------
def _solver(tgt: Target) -> str:
    if tgt.backend != "cvxpy":
        raise BalustradeError(f"target {tgt.name!r}: synthesis problems are SDPs and need the "
                              f"cvxpy backend, not {tgt.backend}")
    return (tgt.solver or "CLARABEL").upper()


def _psd_sizes(prob: cp.Problem) -> list[int]:
    return sorted({int(c.args[0].shape[0]) for c in prob.constraints
                   if isinstance(c, cp.constraints.PSD)}, reverse=True)


def solve_structured(sdp: StructuredSDP, target: Target | str | None = None,
                     lmi: str = "banded") -> StructuredSolution:
    """Lower ``sdp`` with the arrow LMIs in the form ``lmi`` (module docstring) and solve it
    with ``target`` (default ``"clarabel"``). Never raises on a failed solve: the status
    says it (``optimal``, ``optimal_inaccurate``, cvxpy's other statuses, ``solver_error: …``,
    ``too_large``); ``info`` holds the form used (``lmi``), why banded coordinates did not apply
    (``banded_fallback``), the PSD cone sizes and a ``message``."""
    t0 = time.perf_counter()
    if lmi not in LMI_FORMS:
        raise BalustradeError(f"lmi: expected one of {LMI_FORMS}, got {lmi!r}")
    tgt = resolve_target(target, default="clarabel")
    solver = _solver(tgt)
    low = _Lowering(sdp)
    form = "single" if lmi == "single" else "split"
    reason: str | None = None
    cons: list[cp.Constraint] = []
    if low.s is not None and any(sdp.nonneg):
        cons.append(low.s[np.flatnonzero(sdp.nonneg)] >= 0)
    for blk in sdp.blocks:
        if isinstance(blk, NormRows):
            cons += _norm_rows(low, blk)
            continue
        a = None if blk.a is None else low.scalar(blk.a)
        y = None if blk.y is None else low.vector(blk.y)
        if lmi == "banded":
            out = _banded(low, blk, a, y)
            if not isinstance(out, NotBanded):
                cons += out
                form = "banded"
                continue
            reason = out.reason
        leaves = _leaves(low, blk)
        if leaves is None:
            refusal = _dense_cone_refusal(sdp.name, blk.size, solver)
            if refusal is not None:
                return StructuredSolution("too_large", info={
                    "message": refusal, "psd_cone_sizes": [blk.size], "lmi": form,
                    "banded_fallback": reason, "total_time": time.perf_counter() - t0})
            D = low.combination(blk.D)
            D = 0.5 * (D + D.T)
            b = low.combination(blk.b) if blk.b else None
            leaves = [_Leaf(D, low.matrix(blk.L), b)]
            cons += _arrow(blk.L.shape[0], leaves, a, y, split=False)
        else:
            cons += _arrow(blk.L.shape[0], leaves, a, y, split=form != "single")
    objective = _objective(low, sdp)
    prob = cp.Problem(cp.Minimize(objective), cons)
    opts = tgt.solver_options()
    if solver == "CLARABEL" and form == "split":
        # the split is already the chordal decomposition; Clarabel's own merging of the
        # cones only enlarges them again (measured 2.5x slower)
        opts.setdefault("chordal_decomposition_enable", False)
    try:
        prob.solve(solver=solver, **opts)
        status = str(prob.status)
    except cp.error.SolverError as exc:
        status = f"solver_error: {exc}"
    total = time.perf_counter() - t0
    stats = getattr(prob, "solver_stats", None)
    solve_time = float(stats.solve_time) if stats is not None and stats.solve_time else total
    sol = StructuredSolution(status, solve_time=solve_time,
                             info={"n_theta": sdp.n_theta, "psd_cone_sizes": _psd_sizes(prob),
                                   "lmi": form, "banded_fallback": reason, "solver": solver})
    if status in OK_STATUSES and low.theta.value is not None:
        sol.theta = np.asarray(low.theta.value, dtype=float)
        sol.scalars = (np.zeros(0) if low.s is None
                       else np.asarray(low.s.value, dtype=float))
        sol.objective = _objective_value(sdp, sol.theta, sol.scalars)
    sol.info["total_time"] = time.perf_counter() - t0
    return sol


def _objective(low: _Lowering, sdp: StructuredSDP) -> cp.Expression:
    obj = sdp.objective
    if obj is None:
        raise BalustradeError(f"{sdp.name}: no objective (call minimize)")
    if isinstance(obj, Scalar):
        return low.scalar(obj)
    return sum(cp.sum_squares(low.vector(m)) for m in obj)    # type: ignore[return-value]


def _objective_value(sdp: StructuredSDP, theta: np.ndarray, s: np.ndarray) -> float:
    obj = sdp.objective
    if isinstance(obj, Scalar):
        return sdp.pad(obj).value(s)
    return float(sum(np.sum((m.A @ theta + m.c) ** 2) for m in obj)   # type: ignore[union-attr]
                 + sdp.objective_const)


__all__ = ["LMI_FORMS", "OK_STATUSES", "StructuredSolution", "solve_structured"]
