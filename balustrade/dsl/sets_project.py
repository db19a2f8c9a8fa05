"""Exact Euclidean projections ``Π_S(u) = argmin_{x ∈ S} ‖x − u‖₂`` onto the sets of
:mod:`balustrade.dsl.sets` (used by :meth:`Set.project <balustrade.dsl.sets_base.Set.project>`).

* box ``{lb <= x <= ub}``: componentwise clipping;
* polytope ``{Hx <= h}``: the least-distance program ``min ‖y‖ s.t. −H y >= Hu − h``
  (``x = u + y``), solved exactly through its non-negative least-squares dual (Lawson and
  Hanson, *Solving Least Squares Problems*, Ch. 23, algorithm LDP) with
  :func:`scipy.optimize.nnls` (an active-set method), then polished on the active rows;
* ellipsoid ``{(x − q)ᵀP(x − q) <= 1}``: ``x = q + (I + λP)⁻¹(u − q)`` with the multiplier
  ``λ >= 0`` of the KKT conditions, the root of ``g(λ) = ‖x(λ) − q‖²_P − 1`` (convex and
  decreasing): Newton's method from ``λ = 0`` (monotone, no overshoot), bisection as the
  safeguard.

These are numerical routines of the language, not solver calls: no solver is named and
nothing here depends on a backend (DESIGN.md, "Layout").
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.optimize

from balustrade.errors import BalustradeError

#: feasibility tolerance for "already in the set" and for accepting the polished point
TOL = 1e-12


def project_box(u: np.ndarray, lb: np.ndarray, ub: np.ndarray) -> np.ndarray:
    """``clip(u, lb, ub)``: the projection onto a box (infinite bounds allowed)."""
    return np.clip(u, lb, ub)


def project_polytope(u: np.ndarray, H: np.ndarray, h: np.ndarray, name: str = "polytope"
                     ) -> np.ndarray:
    """The projection of ``u`` onto ``{x : Hx <= h}`` (nonempty) by algorithm LDP."""
    norms = np.linalg.norm(H, axis=1)
    keep = norms > 0.0
    if np.any(h[~keep] < -TOL):
        raise BalustradeError(f"{name}.project: the polytope has a row 0ᵀx <= h with h < 0 "
                              "(it is empty)")
    H, h = H[keep] / norms[keep, None], h[keep] / norms[keep]   # unit rows: better conditioned
    if H.shape[0] == 0 or np.all(H @ u - h <= TOL):
        return u.copy()
    n = u.size
    g = H @ u - h                                               # −H y >= g
    E = np.vstack([-H.T, g.reshape(1, -1)])                     # (n + 1) × m
    f = np.zeros(n + 1)
    f[n] = 1.0
    z, _ = scipy.optimize.nnls(E, f, maxiter=50 * max(E.shape))
    r = E @ z - f
    if abs(r[n]) <= 1e-14:
        raise BalustradeError(f"{name}.project: the least-distance problem is infeasible (the "
                              "polytope is empty up to rounding)")
    x = u - r[:n] / r[n]
    return _polish(u, x, H, h)


def _polish(u: np.ndarray, x: np.ndarray, H: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Re-solve the projection onto the affine hull of the rows active at ``x`` (exact
    linear algebra); keep it if it is feasible and its multipliers are nonnegative (then
    it satisfies the KKT conditions), else keep ``x``."""
    active = np.flatnonzero(H @ x - h >= -1e-9)
    if active.size == 0:
        return x
    A, b = H[active], h[active]
    lam, *_ = np.linalg.lstsq(A @ A.T, A @ u - b, rcond=None)
    y = u - A.T @ lam
    if np.all(lam >= -1e-12) and np.all(H @ y - h <= TOL):
        return y
    return x


def project_ellipsoid(u: np.ndarray, P: np.ndarray, center: np.ndarray) -> np.ndarray:
    """The projection of ``u`` onto ``{x : (x − q)ᵀP(x − q) <= 1}`` (``P ≻ 0``)."""
    d = u - center
    if d @ P @ d <= 1.0:
        return u.copy()
    mu, V = np.linalg.eigh(P)
    a = V.T @ d

    def g(lam: float) -> float:
        y = a / (1.0 + lam * mu)
        return float(np.sum(mu * y * y) - 1.0)

    # g is convex and decreasing on λ >= 0 with g(0) > 0: Newton from the left never
    # overshoots the root and converges quadratically; bisection is the safeguard
    lam = 0.0
    for _ in range(100):
        y = a / (1.0 + lam * mu)
        val = float(np.sum(mu * y * y) - 1.0)
        if val <= 0.0:
            break
        slope = -2.0 * float(np.sum(mu * mu * y * y / (1.0 + lam * mu)))
        step = -val / slope
        if not np.isfinite(step) or step <= 1e-15 * (1.0 + lam):
            break
        lam += step
    else:
        lam = _bisect(g, lam)
    return center + V @ (a / (1.0 + lam * mu))


def _bisect(g: Callable[[float], float], lo: float) -> float:
    """The root of the decreasing ``g`` right of ``lo`` (``g(lo) > 0``), feasible side."""
    hi = 2.0 * lo + 1.0
    while g(hi) > 0.0:
        lo, hi = hi, 2.0 * hi
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if mid <= lo or mid >= hi:
            break
        if g(mid) > 0.0:
            lo = mid
        else:
            hi = mid
    return hi


__all__ = ["project_box", "project_ellipsoid", "project_polytope"]
