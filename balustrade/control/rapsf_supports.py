"""``s_jr = max_{x∈𝕏₀} [H_X]_r A_cl(θ^j) x`` (SPEC §2.20) for a polytope ``𝕏₀`` whose vertices
are not enumerated (more than 6 states: the 5-mass chain's contractive polytope, 30 rows in
10 states), recomputed by Algorithm 4.1 for every new ``Θ_k``.

:class:`LearnedSupports` remembers the vertices of ``𝕏₀`` at which earlier LPs ended, with
their active rows. For a new direction ``d`` the best remembered vertex ``v`` gives a lower
bound ``dᵀv``; the multipliers ``y`` of its active rows (``H_Aᵀ y = d``) give an upper bound
by weak duality over a box that provably contains ``𝕏₀``
(:func:`~balustrade.dsl.sets_geometry.verified_upper`, the bound
:meth:`Polytope.support <balustrade.dsl.sets.Polytope.support>` returns). When the two agree
within :data:`VERIFY_GAP` (relative), ``v`` is optimal for ``d`` to that accuracy and the upper
bound is the value, with no LP; every other direction goes to the LPs
(:func:`~balustrade.backends.lp.verified_supports`, one solver run), whose maximisers become
new remembered vertices. Between steps ``Θ_k`` shrinks a little, so the optimal vertex of
most rows stays the same.

The returned value is always a verified upper bound of the support (a solver tolerance or a
wrongly remembered basis can only make the gap test fail, sending the row to an LP), and
within :data:`VERIFY_GAP` of the value of a point of ``𝕏₀`` — as tight as the LP optimum it
replaces.
"""

from __future__ import annotations

import numpy as np

from balustrade.backends.lp import verified_supports
from balustrade.dsl.sets import Polytope

#: a remembered vertex answers a direction when its verified upper bound exceeds its value
#: by at most this, relative to ``1 + |value|`` (as the box update's vertex bounds,
#: :data:`balustrade.estimate.updates.VERIFY_GAP`)
VERIFY_GAP = 1e-9

#: a row is active at an LP's maximiser when ``H_i x >= h_i − ACTIVE_TOL (1 + |h_i|)``
ACTIVE_TOL = 1e-9

#: at most this many vertices are remembered (the oldest are dropped first)
MAX_VERTICES = 2000


class LearnedSupports:
    """``max_{x∈P} d_rᵀx`` for the rows of ``D``, over one bounded polytope ``P`` (module
    docstring). ``lps`` counts the directions that needed an LP, ``reused`` those answered by
    a remembered vertex (for tests and benchmarks)."""

    def __init__(self, P: Polytope):
        self.H, self.h = np.asarray(P.H, dtype=float), np.asarray(P.h, dtype=float)
        self.box = P.verified_box()
        self.n = self.H.shape[1]
        self.vertices = np.zeros((0, self.n))
        self._rows: list[np.ndarray] = []        # active rows of each vertex (n of them)
        self._inv: list[np.ndarray] = []         # H_A⁻¹ of those rows
        self.lps = self.reused = 0

    def __call__(self, D: np.ndarray) -> np.ndarray | None:
        """The supports along the rows of ``D``; ``None`` when an LP did not end optimal
        (the caller then computes them row by row)."""
        D = np.atleast_2d(np.asarray(D, dtype=float))
        values = np.full(len(D), np.nan)
        todo = np.ones(len(D), dtype=bool)
        if len(self.vertices) and self.box is not None:
            todo = ~self._from_vertices(D, values)
        if np.any(todo):
            got = verified_supports(D[todo], self.H, self.h, self.box, points=True)
            if got is None:
                return None
            values[todo], X = got
            for x in X:
                self._remember(x)
        self.lps += int(todo.sum())
        self.reused += int(len(D) - todo.sum())
        return values

    def _from_vertices(self, D: np.ndarray, values: np.ndarray) -> np.ndarray:
        """Fill ``values`` where a remembered vertex is verified optimal; returns where."""
        scores = D @ self.vertices.T
        best = scores.argmax(axis=1)
        lower = scores[np.arange(len(D)), best]
        upper = np.full(len(D), np.inf)
        lb, ub = self.box
        for j in np.unique(best):
            sel = np.flatnonzero(best == j)
            Y = np.zeros((sel.size, self.H.shape[0]))
            Y[:, self._rows[j]] = D[sel] @ self._inv[j]       # H_Aᵀ y = d  ⇔  yᵀ = dᵀ H_A⁻¹
            Y = np.maximum(Y, 0.0)                              # verified_upper, row by row
            R = D[sel] - Y @ self.H
            upper[sel] = Y @ self.h + np.maximum(R * lb, R * ub).sum(axis=1)
        ok = upper - lower <= VERIFY_GAP * (1.0 + np.abs(lower))
        values[ok] = np.maximum(upper[ok], lower[ok])
        return ok

    def _remember(self, x: np.ndarray) -> None:
        """Keep the vertex an LP ended at when exactly ``n`` rows are active there and they
        are well conditioned (the vertex is recomputed from them and checked feasible)."""
        slack = self.h - self.H @ x
        rows = np.flatnonzero(slack <= ACTIVE_TOL * (1.0 + np.abs(self.h)))
        if rows.size != self.n:
            return
        HA = self.H[rows]
        if np.linalg.cond(HA) > 1e10:
            return
        inv = np.linalg.inv(HA)
        v = inv @ self.h[rows]
        if np.any(self.H @ v - self.h > ACTIVE_TOL * (1.0 + np.abs(self.h))):
            return
        if len(self.vertices) and np.min(np.abs(self.vertices - v).max(axis=1)) <= 1e-12:
            return
        if len(self.vertices) >= MAX_VERTICES:
            self.vertices, self._rows, self._inv = self.vertices[1:], self._rows[1:], \
                self._inv[1:]
        self.vertices = np.vstack([self.vertices, v])
        self._rows.append(rows)
        self._inv.append(inv)


__all__ = ["LearnedSupports"]
