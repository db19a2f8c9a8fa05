"""Convex-hull membership of points by LPs (the pruning of SPEC §2.22's enlarged terminal set).

``co(V)`` is given by its generators ``V`` (columns). The distance of a point ``c`` to
``co(V)`` in the 1-norm is the value of the separation LP

    ``max_{a, b}  aᵀc − b   s.t.  aᵀv_g <= b  for every generator g,  −1 <= a <= 1``

(``b`` free): ``max_{‖a‖∞<=1} (aᵀc − max_g aᵀv_g) = min_{y∈co V} ‖c − y‖₁`` by LP duality. The
feasible set depends on ``V`` only, so the distances of many points are one LP model with a
changing cost (:func:`balustrade.backends.lp.solve_lps`, warm-started), not one model per point.

* :func:`hull_distances` — the 1-norm distances of points to ``co(V)`` (0 inside);
* :func:`extreme_points` — the generators that are not in the hull of the others (one model per
  generator, i.e. ``G`` LPs of ``G`` rows).
"""

from __future__ import annotations

import numpy as np

from balustrade.backends.lp import _dense_model, _highs, solve_lps
from balustrade.backends.solution import Status
from balustrade.errors import BalustradeError, ShapeError

#: :func:`extreme_points` screens by random directions only above this many generators (the
#: screen costs one LP per generator itself: it pays off when most are inside the hull)
SCREEN_MIN = 128


def _separation_set(V: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``{(a, b) : Vᵀa − b <= 0, −1 <= a <= 1}`` as ``H [a; b] <= h``."""
    d, G = V.shape
    eye = np.eye(d)
    H = np.vstack([np.hstack([V.T, -np.ones((G, 1))]),
                   np.hstack([eye, np.zeros((d, 1))]),
                   np.hstack([-eye, np.zeros((d, 1))])])
    return H, np.concatenate([np.zeros(G), np.ones(2 * d)])


def hull_distances(points: np.ndarray, V: np.ndarray) -> np.ndarray:
    """``min_{y∈co V} ‖p − y‖₁`` for every column ``p`` of ``points`` (``d × P``), ``V``
    ``d × G`` with ``G >= 1``; ``0`` (up to the LP tolerance) for points in the hull.
    Raises :class:`~balustrade.errors.BalustradeError` when an LP does not end optimal."""
    points = np.atleast_2d(np.asarray(points, dtype=float))
    V = np.atleast_2d(np.asarray(V, dtype=float))
    if V.shape[1] == 0:
        raise ShapeError("hull_distances: V", "at least one generator (column)", V.shape)
    if points.shape[0] != V.shape[0]:
        raise ShapeError("hull_distances: points", f"{V.shape[0]} rows (as V)", points.shape)
    if points.shape[1] == 0:
        return np.zeros(0)
    H, h = _separation_set(V)
    C = np.hstack([points.T, -np.ones((points.shape[1], 1))])
    res = solve_lps(C, H, h, maximize=True)
    if len(res) < len(C) or any(r.status is not Status.OPTIMAL for r in res):
        bad = next((r.status for r in res if r.status is not Status.OPTIMAL), "missing")
        raise BalustradeError(f"hull_distances: a separation LP ended {bad}")
    return np.maximum(np.array([r.value for r in res]), 0.0)


def extreme_points(V: np.ndarray, tol: float = 1e-9, fixed: np.ndarray | None = None
                   ) -> np.ndarray:
    """A boolean mask over the columns of ``V``: ``True`` for a generator whose distance to
    the hull of the other kept generators (and of the columns of ``fixed``, which are never
    pruned) exceeds ``tol·(1 + ‖v‖₁)``. Generators are tested in order and a pruned one no
    longer counts as "other", so duplicates keep exactly one copy.

    Many generators (more than ``max(4(d + 1), SCREEN_MIN)``) are first screened: the
    maximisers of ``±e_i`` and ``8d`` fixed random directions are extreme, and every
    generator inside their hull (one warm LP model for all) is not; only the rest is tested
    one by one."""
    V = np.atleast_2d(np.asarray(V, dtype=float))
    d, G = V.shape
    F = np.zeros((d, 0)) if fixed is None else np.atleast_2d(np.asarray(fixed, dtype=float))
    if F.shape[0] != d:
        raise ShapeError("extreme_points: fixed", f"{d} rows (as V)", F.shape)
    todo = np.arange(G)
    if G > max(4 * (d + 1), SCREEN_MIN):
        D = np.vstack([np.eye(d), -np.eye(d), np.random.default_rng(0).normal(size=(8 * d, d))])
        E = np.unique(np.argmax(D @ V, axis=1))
        dist = hull_distances(V, np.hstack([V[:, E], F]))
        out = dist > tol * (1.0 + np.abs(V).sum(axis=0))
        out[E] = True
        todo = np.flatnonzero(out)
    keep = _prune_warm(V, F, todo, tol)
    if keep is not None:
        return keep
    keep = np.zeros(G, dtype=bool)
    keep[todo] = True
    for g in todo:
        keep[g] = False
        others = np.hstack([V[:, keep], F])
        if others.shape[1] == 0:
            keep[g] = True
            continue
        dist = hull_distances(V[:, g:g + 1], others)[0]
        keep[g] = dist > tol * (1.0 + float(np.abs(V[:, g]).sum()))
    return keep


def _prune_warm(V: np.ndarray, F: np.ndarray, todo: np.ndarray, tol: float
                ) -> np.ndarray | None:
    """The one-by-one test of :func:`extreme_points` in one HiGHS model: the separation set
    of all generators, where testing ``g`` frees its own row and a pruned generator's row
    stays free; only the cost and one row bound change between the LPs (warm starts).
    ``None`` without ``highspy`` or when an LP does not end optimal (then the caller tests
    with fresh models)."""
    try:
        import highspy
    except ImportError:  # pragma: no cover - highspy ships with the test environment
        return None
    d, G = V.shape
    H, h = _separation_set(np.hstack([V, F]))
    solver = _highs(highspy)
    nc = H.shape[1]
    upper = np.asarray(h, dtype=float).copy()
    active = np.zeros(G, dtype=bool)
    active[todo] = True
    upper[:G][~active] = highspy.kHighsInf
    lp = _dense_model(highspy, H, upper)
    lp.sense_ = highspy.ObjSense.kMaximize
    solver.clearModel()
    solver.passModel(lp)
    cols = np.arange(nc, dtype=np.int32)
    n_fixed = F.shape[1]
    for g in todo:
        active[g] = False
        solver.changeRowBounds(int(g), -highspy.kHighsInf, highspy.kHighsInf)
        if not active.any() and n_fixed == 0:
            keep_g = True                                   # nothing else to be inside of
        else:
            c = np.append(V[:, g], -1.0)
            solver.changeColsCost(nc, cols, c)
            solver.run()
            if str(solver.getModelStatus()).rsplit(".", 1)[-1] != "kOptimal":
                return None
            dist = float(c @ np.asarray(solver.getSolution().col_value, dtype=float))
            keep_g = dist > tol * (1.0 + float(np.abs(V[:, g]).sum()))
        if keep_g:
            active[g] = True
            solver.changeRowBounds(int(g), -highspy.kHighsInf, 0.0)
    return active


__all__ = ["extreme_points", "hull_distances"]
