"""``Θ_new ⊆ Θ_old`` by support functions: one LP per row of ``Θ_old`` (none for boxes), the
nesting half of Assumption 4.2 (SPEC §2.19, "accept a new set only if it is contained in the
previous one")."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from balustrade.backends.lp import solve_lp
from balustrade.backends.solution import Status
from balustrade.dsl.sets import Box, Polytope


@dataclass(frozen=True)
class Containment:
    """``nested``; ``lps`` solved; ``excess`` = max over rows of ``h_new_support − h_old``
    (``<= tol`` when nested); ``row`` the worst row of ``Θ_old`` and ``reason`` in words."""

    nested: bool
    lps: int
    excess: float
    row: int
    reason: str


def contained_in(new: Polytope, old: Polytope, tol: float = 1e-9) -> Containment:
    """Whether ``new ⊆ old``: ``max {H_old[r] θ : θ ∈ new} <= h_old[r] + tol`` for every row
    ``r``. Boxes are compared by their bounds; rows of ``old`` that ``new`` repeats with a
    bound at least as tight need no LP."""
    if isinstance(new, Box) and isinstance(old, Box):
        ex = np.concatenate([new.ub - old.ub, old.lb - new.lb])
        r = int(np.argmax(ex))
        return _verdict(float(ex[r]), r, 0, tol)
    lps, worst, worst_row = 0, -np.inf, -1
    for r, (a, b) in enumerate(zip(old.H, old.h, strict=True)):
        same = np.all(np.abs(new.H - a) <= 1e-12, axis=1) & (new.h <= b + 1e-12)
        if np.any(same):
            excess = float(np.min(new.h[same]) - b)
        elif isinstance(new, Box):
            excess = new.support(a) - b
        else:
            res = solve_lp(a, new.H, new.h)
            lps += 1
            if res.status is not Status.OPTIMAL:
                return Containment(False, lps, float("inf"), r,
                                   f"the support LP of row {r} of the previous set ended "
                                   f"{res.status.value}")
            excess = res.value - b
        if excess > worst:
            worst, worst_row = excess, r
    return _verdict(worst, worst_row, lps, tol)


def _verdict(excess: float, row: int, lps: int, tol: float) -> Containment:
    if excess <= tol:
        return Containment(True, lps, excess, row, "")
    return Containment(False, lps, excess, row,
                       f"not nested: the new set exceeds row {row} of the previous set by "
                       f"{excess:.3g}")


def bounding_box(P: Polytope) -> tuple[np.ndarray, np.ndarray, int, bool]:
    """``(lb, ub, lps, ok)``: the bounding box of ``P`` (``2q`` LPs, none for a box)."""
    if isinstance(P, Box):
        return P.lb.copy(), P.ub.copy(), 0, True
    q = P.dim
    lb, ub = np.empty(q), np.empty(q)
    for j in range(q):
        e = np.eye(q)[j]
        hi, lo = solve_lp(e, P.H, P.h), solve_lp(e, P.H, P.h, maximize=False)
        if hi.status is not Status.OPTIMAL or lo.status is not Status.OPTIMAL:
            return np.full(q, np.nan), np.full(q, np.nan), 2 * j + 2, False
        lb[j], ub[j] = lo.value, hi.value
    return lb, ub, 2 * q, True


__all__ = ["Containment", "bounding_box", "contained_in"]
