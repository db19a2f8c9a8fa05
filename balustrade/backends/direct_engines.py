"""The solver objects of the direct backend: Clarabel and PIQP through their own interfaces,
set up once from a :class:`~balustrade.backends.passes.to_conic.ConicProgram` (``P``, ``A``
and the cones), then only the vectors ``q``, ``b`` are updated per solve — and the values of
``A`` on its fixed sparsity pattern when ``A`` depends on the parameters
(:attr:`~balustrade.backends.passes.to_conic.ConicProgram.A_param`): Clarabel takes the new
nonzero values directly (``update(A=values)``, its equilibration of the set-up data applied
to them), PIQP the equality and inequality blocks as matrices with the set-up pattern.

Each solve starts from the solver's own initial point: Clarabel (presolve and structural-zero
dropping off, so that data updates are allowed) keeps nothing but the equilibration of the
data it was set up with; PIQP re-equilibrates on each update
(``preconditioner_reuse_on_update`` off). Neither exposes a warm start through its Python
interface, so the answer of a solve depends on its parameters only (history independence,
issue #12 item 3). The opt-in DAQP engine (:mod:`~balustrade.backends.daqp_engine`) is the
exception: it starts each solve from the previous one's working set (its answers are KKT-checked;
the optimal point, not the optimal value, may depend on the history).
"""

from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp

from balustrade.backends.passes.to_conic import ConicProgram
from balustrade.backends.solution import Status
from balustrade.errors import SolverError

#: the solvers of the direct backend ("daqp": the opt-in hot-started dense active-set engine
#: of :mod:`~balustrade.backends.daqp_engine`, checked and backed by PIQP)
DIRECT_SOLVERS = ("clarabel", "piqp", "daqp")

#: tolerances. PIQP: tight, as :data:`balustrade.backends.cvxpy_backend.SOLVER_OPTIONS`.
#: Clarabel: the feasibility tolerance stays tight (1e-10: the rows, e.g. the decrease bound
#: (6.15g) with its 1e-9 margin, hold to it), the duality gap 1e-9 (was 1e-10). Measured on
#: the rendezvous (N = 200, the states of ``bench_robust``, ``docs/engines.md``): the gap
#: alone sets the iteration count (1e-10 / 1e-9: 13/10/16 vs 12/9/12 median iterations for
#: (5.15)/(5.16)/(6.15); the feasibility and KKT-ratio tolerances change none). Clarabel's
#: own default 1e-8 would match the hand-written baseline's iterations but breaks the 1e-6
#: agreement with cvxpy of ``test_rendezvous_robust_pair_agrees_with_cvxpy`` (α_f = 1e6
#: times a 1e-12 bound violation), so it is not used.
DEFAULT_OPTIONS: dict[str, dict] = {
    "clarabel": {"tol_gap_abs": 1e-9, "tol_gap_rel": 1e-9, "tol_feas": 1e-10,
                 "tol_ktratio": 1e-8, "max_iter": 300},
    "piqp": {"eps_abs": 1e-10, "eps_rel": 1e-11, "max_iter": 500},
}


def all_finite(v: np.ndarray | list | None) -> bool:
    """Whether ``v`` exists and every entry is finite. A Python list of floats (Clarabel's
    multipliers as its binding returns them) is decided by its sum, without building an
    array: IEEE arithmetic keeps a NaN or an infinity in a running sum (``inf + x = inf``,
    ``inf − inf = nan``, ``nan + x = nan``), so a finite sum means finite entries; only a
    non-finite sum (a non-finite entry, or finite entries whose sum overflows) is checked
    entry by entry."""
    if v is None:
        return False
    if isinstance(v, list):
        if math.isfinite(sum(v)):
            return True
        v = np.array(v, dtype=float)
    return bool(np.all(np.isfinite(v)))


class RawResult:
    """One solver run: status, the solver's own words, ``y``, the cone duals ``z`` (the
    multipliers of ``A y + s = b`` with ``P y + q + Aᵀz = 0``), iterations, and ``solver``:
    the solver that answered when it is not the engine's own (e.g. ``"piqp"`` after the DAQP
    engine's fallback), ``None`` otherwise.

    ``z`` may be given as the Python list a solver binding returns: it becomes an array only
    when read (a solve whose multipliers nobody reads does not pay the conversion, ~0.2–0.4
    ms for the 7–8·10³ multipliers of the rendezvous at N = 200); its finiteness is checked
    at once either way (:func:`all_finite`)."""

    def __init__(self, status: Status, words: str, y: np.ndarray | None,
                 z: np.ndarray | list | None, iterations: int, solver: str | None = None):
        self.status, self.words, self.y, self.iterations = status, words, y, iterations
        self.solver = solver
        self._z = z
        # a "solved" verdict with a missing or non-finite point or multipliers is a
        # failure: a NaN never passes as an optimal answer
        if self.status.success and not (all_finite(self.y) and all_finite(self._z)):
            self.status = Status.FAILED
            self.words += "; but the point or its multipliers are not finite"

    @property
    def z(self) -> np.ndarray | None:
        if isinstance(self._z, list):
            self._z = np.fromiter(self._z, dtype=float, count=len(self._z))
        return self._z

    @z.setter
    def z(self, value: np.ndarray | None) -> None:
        self._z = value

    def __repr__(self) -> str:
        return (f"RawResult(status={self.status!r}, words={self.words!r}, "
                f"iterations={self.iterations})")


def _set_options(settings: object, options: dict, solver: str) -> None:
    """Set ``options`` on a solver's settings object; an unknown name or a value of the
    wrong type is a :class:`SolverError` naming the option (not the binding's TypeError)."""
    for key, value in options.items():
        if not isinstance(key, str) or key.startswith("_") or not hasattr(settings, key):
            raise SolverError(f"direct backend: unknown {solver} option {key!r}")
        try:
            setattr(settings, key, value)
        except (TypeError, ValueError, OverflowError) as exc:
            raise SolverError(f"direct backend: {solver} option {key!r} cannot be "
                              f"{value!r} ({type(value).__name__}): {exc}") from None


_CLARABEL_STATUS = {
    "Solved": Status.OPTIMAL, "AlmostSolved": Status.OPTIMAL_INACCURATE,
    "PrimalInfeasible": Status.INFEASIBLE, "MaxIterations": Status.MAX_ITERATIONS,
    "MaxTime": Status.MAX_ITERATIONS,
}
#: a PIQP or Clarabel "optimal" whose point misses a zero or nonnegative-cone row by more
#: than this in the row's own unit (the row divided by ``max_j |a_ij|``, relative to
#: ``1 + |b_i|/max_j |a_ij|``) is reported ``optimal_inaccurate``: the solvers measure
#: feasibility in their scaled problems, where a row ``1e-9·(y₀ + y₃) = 1e-9·β`` next to rows
#: of size 1e6 was missed by 2.2 (PIQP: objective −2.67 instead of 0.656; audit E, session
#: 15). (4.5) of 3 masses: the largest such miss of PIQP's optimal answers was 6.6e-11 (110
#: answers, /work/briefs/s15/audit/e_piqp_rowcheck.py)
ROW_TOL = 1e-6
PIQP_ROW_TOL = ROW_TOL
_PIQP_STATUS = {
    "PIQP_SOLVED": Status.OPTIMAL, "PIQP_PRIMAL_INFEASIBLE": Status.INFEASIBLE,
    "PIQP_MAX_ITER_REACHED": Status.MAX_ITERATIONS,
}


class ClarabelEngine:
    """``clarabel.DefaultSolver`` set up once; :meth:`run` updates ``q``, ``b`` (and the
    values of ``A`` when given) and solves."""

    name = "clarabel"

    def __init__(self, prog: ConicProgram, options: dict, P: sp.csc_matrix | None = None,
                 q: np.ndarray | None = None):
        import clarabel

        settings = clarabel.DefaultSettings()
        settings.verbose = False
        settings.presolve_enable = False  # else data updates are refused
        settings.input_sparse_dropzeros = False
        _set_options(settings, {**DEFAULT_OPTIONS["clarabel"], **options}, "Clarabel")
        cones = [{"zero": clarabel.ZeroConeT, "nonneg": clarabel.NonnegativeConeT,
                  "soc": clarabel.SecondOrderConeT}[kind](m) for kind, m in prog.cones]
        A = prog.A if prog.A.shape[0] else sp.csc_matrix((0, prog.n_y))
        self.solver = clarabel.DefaultSolver(prog.P if P is None else P,
                                             prog.q0 if q is None else q, A, prog.b0,
                                             cones, settings)
        if not self.solver.is_data_update_allowed():
            raise SolverError("direct backend: Clarabel refuses data updates with these "
                              "settings (presolve or dropped structural zeros)")
        #: the ``q`` the solver holds (its update re-scales it: skipped when unchanged)
        self._q = np.array(prog.q0 if q is None else q, dtype=float)
        self._rows = RowMiss(prog)

    def run(self, q: np.ndarray, b: np.ndarray, A: np.ndarray | None = None) -> RawResult:
        """Solve with ``q``, ``b`` (and the values of ``A``); ``q`` is handed to Clarabel only
        when it differs from the one it holds (the same data either way)."""
        data = {"b": b} if A is None else {"b": b, "A": A}
        if q.shape != self._q.shape or not np.array_equal(q, self._q):
            data["q"] = q
            self._q = np.array(q, dtype=float)
        self.solver.update(**data)
        if A is not None:
            self._rows.update(A)
        sol = self.solver.solve()
        words = str(sol.status)
        status = _CLARABEL_STATUS.get(words, Status.FAILED)
        if words == "AlmostPrimalInfeasible":
            words += "; infeasibility not certified"
        elif words in ("DualInfeasible", "AlmostDualInfeasible"):
            words += "; the problem looks unbounded"
        x = sol.x  # the binding builds a new list on every read: once each
        y = np.fromiter(x, dtype=float, count=len(x))
        status, words = self._rows.verdict(status, words, y, b)
        return RawResult(status, f"Clarabel: {words}", y, sol.z, int(sol.iterations))


class PiqpEngine:
    """``piqp.SparseSolver`` set up once for an LP/QP (zero rows → ``A y = b``, nonnegative
    rows → ``G y <= h``); :meth:`run` updates ``c``, ``b``, ``h_u`` and solves."""

    name = "piqp"

    def __init__(self, prog: ConicProgram, options: dict, P: sp.csc_matrix | None = None,
                 q: np.ndarray | None = None):
        import piqp

        if prog.conic:
            raise SolverError("direct backend: PIQP takes LPs and QPs only; this problem "
                              "needs a second-order cone (use solver 'clarabel')")
        self.m0 = sum(m for kind, m in prog.cones if kind == "zero")
        self.has_eq = self.m0 > 0
        self.has_ineq = prog.A.shape[0] > self.m0
        self._blocks = _row_blocks(prog.A, self.m0)
        self._mats: tuple[sp.csc_matrix | None, sp.csc_matrix | None] | None = None
        A_eq, A_ineq = self._matrices(prog.A.data)
        self.solver = piqp.SparseSolver()
        self.solver.settings.verbose = False
        self.solver.settings.preconditioner_reuse_on_update = False
        _set_options(self.solver.settings, {**DEFAULT_OPTIONS["piqp"], **options}, "PIQP")
        Pfull = prog.P if P is None else P
        Pfull = sp.triu(Pfull).tocsc()  # PIQP reads the upper triangle
        q0 = prog.q0 if q is None else q
        b = prog.b0
        self.solver.setup(Pfull, q0, A_eq, b[:self.m0] if self.has_eq else None,
                          A_ineq, None, b[self.m0:] if self.has_ineq else None)
        self._rows = RowMiss(prog)

    def _matrices(self, values: np.ndarray) -> tuple[sp.csc_matrix | None,
                                                     sp.csc_matrix | None]:
        """The equality and inequality blocks of ``A`` with the nonzero values ``values``
        (in the order of ``A.data``), always on the set-up pattern (explicit zeros kept: an
        update with another pattern would be taken silently and wrongly). The two matrices
        are built once and only their values overwritten (scipy's constructor checks cost
        more than PIQP's update of a small problem)."""
        if self._mats is None:
            self._mats = tuple(
                sp.csc_matrix((values[at], indices, indptr), shape=shape) if used else None
                for (indices, indptr, at, shape), used in
                zip(self._blocks, (self.has_eq, self.has_ineq), strict=True))
        else:
            for mat, (_, _, at, _) in zip(self._mats, self._blocks, strict=True):
                if mat is not None:
                    mat.data[:] = values[at]
        return self._mats

    def run(self, q: np.ndarray, b: np.ndarray, A: np.ndarray | None = None) -> RawResult:
        mats = {}
        if A is not None:
            A_eq, A_ineq = self._matrices(A)
            mats = {k: v for k, v in (("A", A_eq), ("G", A_ineq)) if v is not None}
            self._rows.update(A)
        self.solver.update(c=q, b=b[:self.m0] if self.has_eq else None,
                           h_u=b[self.m0:] if self.has_ineq else None, **mats)
        status_obj = self.solver.solve()
        words = str(status_obj.name)
        if words == "PIQP_DUAL_INFEASIBLE":
            words += "; the problem looks unbounded"
        res = self.solver.result
        parts = []
        if self.has_eq:
            parts.append(np.asarray(res.y, dtype=float))
        if self.has_ineq:
            parts.append(np.asarray(res.z_u, dtype=float) - np.asarray(res.z_l, dtype=float))
        z = np.concatenate(parts) if parts else np.zeros(0)
        x = np.asarray(res.x, dtype=float)
        status, words = self._rows.verdict(_PIQP_STATUS.get(words, Status.FAILED), words, x, b)
        return RawResult(status, f"PIQP: {words}", x, z, int(res.info.iter))


class RowMiss:
    """The misses of the zero-cone rows (``a_iᵀy = b_i``) and nonnegative-cone rows
    (``a_iᵀy <= b_i``) of a lowered program at a point, each in its row's own unit
    (:data:`ROW_TOL`); second-order-cone rows are not checked here. The row norms are one
    reduceat over ``A``'s values in row order, recomputed only when they change (scipy's max
    over axis 1 of a CSC matrix took 0.35 ms on (4.5) of 3 masses, a seventh of a solve)."""

    def __init__(self, prog: ConicProgram):
        A = sp.csc_matrix(prog.A)
        self._pattern = A
        self._order = _row_order(A)
        kinds = np.concatenate([np.full(m, kind) for kind, m in prog.cones]) \
            if prog.cones else np.zeros(0, dtype="<U7")
        self._eq = kinds == "zero"
        self._ineq = kinds == "nonneg"
        self._values: np.ndarray | None = None
        self._matrix = A
        self._norms = self._row_norms(A.data)

    def _row_norms(self, values: np.ndarray) -> np.ndarray:
        perm, starts, rows, m = self._order
        norms = np.ones(m)
        if perm.size:
            norms[rows] = np.maximum.reduceat(np.abs(values[perm]), starts)
        return np.where(norms > 0, norms, 1.0)

    def update(self, values: np.ndarray) -> None:
        """The values of ``A(p)`` (in the order of the program's ``A.data``)."""
        if self._values is not None and np.array_equal(values, self._values):
            return
        self._values = np.array(values, dtype=float)
        p = self._pattern
        self._matrix = sp.csc_matrix((self._values, p.indices, p.indptr), shape=p.shape)
        self._norms = self._row_norms(self._values)

    def miss(self, y: np.ndarray, b: np.ndarray) -> float:
        """The largest miss at ``y``: ``|a_iᵀy − b_i|`` (zero cone) or ``(a_iᵀy − b_i)₊``
        (nonnegative cone, finite ``b_i``), divided by ``n_i + |b_i|`` (``n_i = max_j
        |a_ij|``)."""
        finite = np.isfinite(b)
        rhs = np.where(finite, b, 0.0)
        r = np.where(finite, self._matrix @ y - rhs, 0.0)
        r = np.where(self._eq, np.abs(r), np.where(self._ineq, np.maximum(r, 0.0), 0.0))
        return float(np.max(r / (self._norms + np.abs(rhs)), initial=0.0))

    def verdict(self, status: Status, words: str, y: np.ndarray, b: np.ndarray
                ) -> tuple[Status, str]:
        """``status`` and ``words``, an ``optimal`` made ``optimal_inaccurate`` (words say
        why) when the point misses a row by more than :data:`ROW_TOL`."""
        if status != Status.OPTIMAL:
            return status, words
        miss = self.miss(y, b)
        if miss <= ROW_TOL:
            return status, words
        return Status.OPTIMAL_INACCURATE, (f"{words}; a row missed by {miss:.1e} in its own "
                                           f"unit (> {ROW_TOL:g}: badly scaled rows)")


def _row_order(mat: sp.csc_matrix) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """For ``mat``'s values: the permutation putting them in row order, the start of each
    nonempty row in that order, those rows, and the number of rows."""
    code = sp.csc_matrix((np.arange(1, mat.nnz + 1, dtype=float), mat.indices, mat.indptr),
                         shape=mat.shape).tocsr()        # 1 … nnz: no value is a zero
    code.sort_indices()
    perm = code.data.astype(np.int64) - 1
    counts = np.diff(code.indptr)
    rows = np.flatnonzero(counts > 0)
    return perm, code.indptr[rows].astype(np.int64), rows, mat.shape[0]


def _row_blocks(A: sp.csc_matrix, m0: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray,
                                                          tuple[int, int]]]:
    """The CSC structure of rows ``:m0`` and ``m0:`` of ``A`` and where their nonzeros sit in
    ``A.data`` (found by slicing ``A`` with the values ``1 … nnz``)."""
    code = sp.csc_matrix((np.arange(1, A.nnz + 1, dtype=float), A.indices, A.indptr),
                         shape=A.shape).tocsr()
    out = []
    for part in (code[:m0].tocsc(), code[m0:].tocsc()):
        part.sort_indices()
        out.append((part.indices, part.indptr, part.data.astype(np.int64) - 1, part.shape))
    return out


def make_engine(solver: str, prog: ConicProgram, options: dict, **data) -> object:
    """The engine named ``solver`` for ``prog`` (``data``: ``P``/``q`` replacing the
    program's, for the feasibility and rescaled re-solves)."""
    if solver == "clarabel":
        return ClarabelEngine(prog, options, **data)
    if solver == "piqp":
        return PiqpEngine(prog, options, **data)
    if solver == "daqp":
        from balustrade.backends.daqp_engine import DaqpEngine
        return DaqpEngine(prog, options, **data)
    raise SolverError(f"direct backend: unknown solver {solver!r}; use one of "
                      f"{', '.join(DIRECT_SOLVERS)}")
