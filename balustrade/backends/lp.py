"""Small dense LPs ``max/min cᵀθ s.t. Hθ <= h`` for the set-membership estimators (SPEC §2.19).

The estimators of :mod:`balustrade.estimate` solve a few LPs per step in ``q`` (the parameter
dimension) variables; they name no solver (issue #13 §1), so the solver lives here: SciPy's
HiGHS through :func:`scipy.optimize.linprog`. Statuses are the backends' one
:class:`~balustrade.backends.solution.Status`; a solve that is not optimal is never given a
value.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.optimize

from balustrade.backends.solution import Status

#: SciPy's linprog status -> Status (0 optimal, 1 iteration limit, 2 infeasible, 3 unbounded)
_STATUS = {0: Status.OPTIMAL, 1: Status.MAX_ITERATIONS, 2: Status.INFEASIBLE,
           3: Status.UNBOUNDED}


@dataclass(frozen=True)
class LPResult:
    """``status``; ``value`` the optimal objective and ``x`` a maximiser/minimiser (``nan``
    and ``None`` unless ``status`` is optimal)."""

    status: Status
    value: float
    x: np.ndarray | None


def solve_lp(c: np.ndarray, H: np.ndarray, h: np.ndarray, maximize: bool = True) -> LPResult:
    """``max`` (or ``min``) ``cᵀθ`` over ``{θ : Hθ <= h}``, θ free. Inputs are trusted arrays
    (the callers check shapes); ``H`` may have zero rows."""
    c = np.asarray(c, dtype=float)
    sign = -1.0 if maximize else 1.0
    res = scipy.optimize.linprog(sign * c, A_ub=H if H.shape[0] else None,
                                 b_ub=h if H.shape[0] else None,
                                 bounds=[(None, None)] * c.size, method="highs")
    status = _STATUS.get(res.status, Status.FAILED)
    if status is not Status.OPTIMAL:
        return LPResult(status, float("nan"), None)
    return LPResult(status, float(sign * res.fun), np.asarray(res.x, dtype=float))


def is_feasible(H: np.ndarray, h: np.ndarray) -> Status:
    """``OPTIMAL`` if ``{θ : Hθ <= h}`` is non-empty, ``INFEASIBLE`` if empty (one LP with a
    zero objective); ``FAILED``/``MAX_ITERATIONS`` if the LP could not decide."""
    return solve_lp(np.zeros(H.shape[1]), H, h).status


__all__ = ["LPResult", "is_feasible", "solve_lp"]
