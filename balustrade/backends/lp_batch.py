"""Many feasibility LPs that differ only in their row bounds (admissible-set volumes, thesis
§4.7 Table 4.1).

``{y : r_lo <= A y <= r_hi, c_lo <= y <= c_hi}`` is decided for a batch of row-bound pairs
``(r_lo[s], r_hi[s])`` with one HiGHS model: the matrix is passed once, each sample only
changes the row bounds, and the dual simplex restarts from the previous basis (neighbouring
samples share most of it). A sample HiGHS cannot decide (presolve's "unbounded or
infeasible", an iteration limit) is retried once from scratch through
:func:`scipy.optimize.linprog`; what stays undecided is reported as such, never as feasible.
An ``infeasible`` verdict is re-decided once without presolve (HiGHS' presolve has called
a thin, non-empty set empty: :mod:`balustrade.backends.lp`); a sample the two runs disagree on
takes the second run's verdict.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.optimize
import scipy.sparse

from balustrade.backends.lp import _HIGHS_STATUS, _highs, run_without_presolve
from balustrade.backends.solution import Status

#: per-sample outcome codes of :func:`feasible_many`
FEASIBLE, INFEASIBLE, UNDECIDED = 1, 0, -1


@dataclass(frozen=True)
class BatchLP:
    """The fixed part of the batch: ``A`` (``m × n``, any SciPy sparse or dense matrix) and
    the column bounds (``±inf`` allowed)."""

    A: scipy.sparse.csr_matrix
    col_lb: np.ndarray
    col_ub: np.ndarray

    @classmethod
    def build(cls, A: object, col_lb: np.ndarray, col_ub: np.ndarray) -> BatchLP:
        A = scipy.sparse.csr_matrix(A, dtype=float)
        return cls(A, np.asarray(col_lb, dtype=float).ravel(),
                   np.asarray(col_ub, dtype=float).ravel())


def _model(highspy: object, lp: BatchLP) -> object:
    m, n = lp.A.shape
    model = highspy.HighsLp()
    model.num_col_, model.num_row_ = n, m
    model.col_cost_ = np.zeros(n)
    inf = highspy.kHighsInf
    model.col_lower_ = np.where(np.isfinite(lp.col_lb), lp.col_lb, -inf)
    model.col_upper_ = np.where(np.isfinite(lp.col_ub), lp.col_ub, inf)
    model.row_lower_ = np.full(m, -inf)
    model.row_upper_ = np.full(m, inf)
    M = model.a_matrix_
    M.format_ = highspy.MatrixFormat.kRowwise
    M.start_ = lp.A.indptr.astype(np.int32)
    M.index_ = lp.A.indices.astype(np.int32)
    M.value_ = lp.A.data.astype(float)
    model.a_matrix_ = M
    return model


def _linprog_status(lp: BatchLP, lo: np.ndarray, hi: np.ndarray) -> int:
    """One sample from scratch without presolve, as equality/inequality rows."""
    eq = np.isfinite(lo) & np.isfinite(hi) & (lo == hi)
    up = ~eq & np.isfinite(hi)
    dn = ~eq & np.isfinite(lo)
    A = lp.A
    A_ub = scipy.sparse.vstack([A[up], -A[dn]]) if up.any() or dn.any() else None
    b_ub = np.concatenate([hi[up], -lo[dn]]) if A_ub is not None else None
    res = scipy.optimize.linprog(np.zeros(A.shape[1]), A_ub=A_ub, b_ub=b_ub,
                                 A_eq=A[eq] if eq.any() else None,
                                 b_eq=hi[eq] if eq.any() else None,
                                 bounds=list(zip(np.where(np.isfinite(lp.col_lb), lp.col_lb,
                                                          None),
                                                 np.where(np.isfinite(lp.col_ub), lp.col_ub,
                                                          None), strict=True)),
                                 method="highs", options={"presolve": False})
    return {0: FEASIBLE, 2: INFEASIBLE}.get(res.status, UNDECIDED)


def feasible_many(lp: BatchLP, row_lb: np.ndarray, row_ub: np.ndarray,
                  progress: Callable[[int], None] | None = None,
                  time_limit: float | None = None) -> np.ndarray:
    """Outcome per sample (``FEASIBLE``/``INFEASIBLE``/``UNDECIDED``, an ``int8`` array) of
    ``{y : row_lb[s] <= A y <= row_ub[s], col bounds}``; ``row_lb``, ``row_ub`` are
    ``S × m`` (``±inf`` allowed). ``progress(s)`` is called after every sample.
    ``time_limit`` (seconds per sample, default none): an LP stopped by it is
    ``UNDECIDED`` (not re-solved without a limit) — a large degenerate LP can take HiGHS'
    dual simplex tens of minutes (the 8-mass (4.5) feasibility LP, session 9)."""
    import highspy

    row_lb = np.atleast_2d(np.asarray(row_lb, dtype=float))
    row_ub = np.atleast_2d(np.asarray(row_ub, dtype=float))
    S, m = row_ub.shape
    out = np.full(S, UNDECIDED, dtype=np.int8)
    solver = _highs(highspy)
    solver.clearModel()
    solver.passModel(_model(highspy, lp))
    inf = highspy.kHighsInf
    rows = np.arange(m, dtype=np.int32)
    for s in range(S):
        lo = np.where(np.isfinite(row_lb[s]), row_lb[s], -inf)
        hi = np.where(np.isfinite(row_ub[s]), row_ub[s], inf)
        solver.changeRowsBounds(m, rows, lo, hi)
        if time_limit is not None:   # HiGHS compares it with the object's cumulative clock
            solver.setOptionValue("time_limit", solver.getRunTime() + float(time_limit))
        solver.run()
        word = str(solver.getModelStatus()).rsplit(".", 1)[-1]
        status = _HIGHS_STATUS.get(word, Status.FAILED)
        if word == "kTimeLimit":
            out[s] = UNDECIDED
        elif status is Status.OPTIMAL:
            out[s] = FEASIBLE
        elif status is Status.INFEASIBLE:
            word = run_without_presolve(solver)     # presolve's word is not enough
            out[s] = {"kOptimal": FEASIBLE, "kInfeasible": INFEASIBLE}.get(word, UNDECIDED)
        else:
            out[s] = _linprog_status(lp, row_lb[s], row_ub[s])
        if progress is not None:
            progress(s)
    solver.clearModel()
    if time_limit is not None:
        solver.setOptionValue("time_limit", inf)
    return out


__all__ = ["FEASIBLE", "INFEASIBLE", "UNDECIDED", "BatchLP", "feasible_many"]
