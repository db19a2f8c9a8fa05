"""Fallbacks shared by the closed-loop algorithms (DESIGN.md principle 4: never raise in
the loop): the projection of the proposed input onto ``U`` and the guard for non-finite
measured states."""

from __future__ import annotations

import numpy as np

from balustrade._checks import as_vector
from balustrade.control.base import StepInfo
from balustrade.dsl.sets import Box, Set
from balustrade.errors import NonFiniteError


def finite_state(x: np.ndarray, nx: int | None, block: str) -> np.ndarray | None:
    """``x`` as a checked vector (wrong shapes still raise), or ``None`` if it contains
    NaN or inf, in which case the caller applies :func:`projected_proposal`."""
    try:
        return as_vector(x, block, nx)
    except NonFiniteError:
        return None


def projected_proposal(u_p: np.ndarray, U: Set) -> tuple[np.ndarray, StepInfo]:
    """The last-resort fallback for a non-finite state: ``u_p`` projected onto ``U``."""
    return project(u_p, U), StepInfo(status="non_finite_state", fallback="projected_proposal")


def project(u: np.ndarray, U: Set) -> np.ndarray:
    """Euclidean projection onto ``U`` (clipping for boxes, a small QP otherwise)."""
    u = np.asarray(u, dtype=float).reshape(-1)
    if isinstance(U, Box):
        return np.clip(u, U.lb, U.ub)
    if U.contains(u):
        return u
    import cvxpy as cp

    v = cp.Variable(U.dim)
    H, h = getattr(U, "H", None), getattr(U, "h", None)
    if H is None:
        return u
    cp.Problem(cp.Minimize(cp.sum_squares(v - u)), [H @ v <= h]).solve(solver="CLARABEL")
    return np.asarray(v.value, dtype=float)
