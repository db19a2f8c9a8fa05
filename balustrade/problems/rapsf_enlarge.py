"""The generator pairs of the enlarged terminal set (thesis (4.10), Remark 4.13, SPEC §2.22).

A solved (4.5) with homothetic tubes gives the pairs ``(z*_i, α*_i)``, ``i = 0..N``. By
Theorem 4.12 the hull ``co({(z*_i, α*_i)}_{i, k∈M(k̄)} ∪ 𝕏_f)`` satisfies Assumption 4.11 for
``Θ_k̄`` and every later (nested) parameter set: each pair ``i < N`` has the successor pair
``i + 1`` of the same solution, and ``(z*_N, α*_N)`` lies in the terminal set of that solve.
Remark 4.13 adds the zero-dilation points ``(z*_i + α*_i x^j, 0)`` for the vertices ``x^j`` of
``𝕏₀``: a single state of the tube ``i`` has the same successor pair ``i + 1``.

Pure array functions (the pruning LPs are in :mod:`balustrade.backends.hull`, the online
bookkeeping in :mod:`balustrade.control.rapsf_enlarge`, the offline builder and the check of
Assumption 4.11 in :mod:`balustrade.design.rapsf_enlarge`).
"""

from __future__ import annotations

import numpy as np

from balustrade.dsl.sets_geometry import vertices as polytope_vertices
from balustrade.errors import BalustradeError, NonFiniteError, ShapeError
from balustrade.problems.rapsf import TerminalSet


def tube_pairs(z: np.ndarray, alpha: np.ndarray, n: int | None = None) -> np.ndarray:
    """The pairs ``(z_i, α_i)`` of one solution as columns ``[z; α]`` (``n + 1 × N + 1``);
    ``z`` is ``n × (N + 1)`` and ``alpha`` has ``N + 1`` entries (thesis (4.10))."""
    z = np.asarray(z, dtype=float)
    if z.ndim != 2 or (n is not None and z.shape[0] != n):
        raise ShapeError("tube_pairs: z", "an n × (N + 1) matrix" if n is None
                         else f"a {n} × (N + 1) matrix", z.shape)
    a = np.asarray(alpha, dtype=float).reshape(-1)
    if a.size != z.shape[1]:
        raise ShapeError("tube_pairs: alpha", (z.shape[1],), np.shape(alpha))
    if not (np.all(np.isfinite(z)) and np.all(np.isfinite(a))):
        raise NonFiniteError("tube_pairs: z and alpha must be finite")
    return np.vstack([z, np.maximum(a, 0.0)[None, :]])


def zero_dilation_points(z: np.ndarray, alpha: np.ndarray, X0_vertices: np.ndarray
                         ) -> np.ndarray:
    """Remark 4.13: ``(z_i + α_i x^j, 0)`` for every vertex ``x^j`` (rows of
    ``X0_vertices``) and every ``i``, as columns (``n + 1 × (N + 1)·n₀``)."""
    P = tube_pairs(z, alpha)
    n = P.shape[0] - 1
    X = np.atleast_2d(np.asarray(X0_vertices, dtype=float))
    if X.shape[1] != n:
        raise ShapeError("zero_dilation_points: X0_vertices", f"rows of length n = {n}",
                         X.shape)
    pts = (P[:n, :, None] + P[n][None, :, None] * X.T[:, None, :]).reshape(n, -1)
    return np.vstack([pts, np.zeros((1, pts.shape[1]))])


def base_generators(terminal: TerminalSet | None, n: int) -> np.ndarray | None:
    """The vertices of the base set ``𝕏_f`` as columns ``[z; α]``: ``(0, 0)`` and ``(0, 1)``
    for the default ``z = 0, 0 <= α <= 1``; for ``{H_T z + h_T α <= 1, α >= 0}`` by vertex
    enumeration, or ``None`` when that is not possible (dimension ``n + 1 > 6``, unbounded)."""
    if terminal is None or terminal.H_T is None:
        out = np.zeros((n + 1, 2))
        out[n, 1] = 1.0
        return out
    H_T = np.asarray(terminal.H_T, dtype=float)
    h_T = np.asarray(terminal.h_T, dtype=float).reshape(-1, 1)
    H = np.vstack([np.hstack([H_T, h_T]), -np.eye(n + 1)[n:]])
    try:
        return polytope_vertices(H, np.concatenate([np.ones(H_T.shape[0]), [0.0]]),
                                 "base_generators: terminal set").T
    except BalustradeError:
        return None


__all__ = ["base_generators", "tube_pairs", "zero_dilation_points"]
