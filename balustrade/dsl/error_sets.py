"""Error sets of robust tubes and the constraint tightenings they induce (SPEC §1.4, §1.5, §1.11).

For ``x⁺ = Ax + Bu + Gw`` with ``w ∈ W`` (a bounded polytope or box) and the error feedback
``κ(e) = K e`` the error ``e = x − z`` between the true and the nominal state evolves as
``e⁺ = (A + BK) e + G w``. This module provides

* :func:`bounded_vertices` — the vertices of a bounded disturbance set (the ellipsoidal RPI
  SDP (5.14)/SPEC §1.11 that designs ``E`` and ``K`` is a formulation:
  :func:`balustrade.design.rpi.ellipsoidal_rpi`);
* :func:`minimal_rpi_outer` — the polytopic outer approximation ``F(α, s) = (1−α)⁻¹ ⊕_{i<s}
  A_K^i W`` of the minimal RPI set (Raković et al., 2005) with the ε guarantee
  ``F(α, s) ⊆ F_∞ ⊕ B_∞(ε)``, computed with support functions only;
* :func:`reachable_support` / :func:`reachable_tightened_sets` — the disturbance reachable sets
  ``E_i = ⊕_{j<i} (A+BK)^j W`` of (2.14)/(6.10) as row tightenings
  ``Σ_{j<i} h_W(((A+BK)^j)ᵀ a)`` (no vertices needed);
* :func:`tighten`, :func:`tighten_by_feedback` — ``X ⊖ E`` and ``U ⊖ K E`` for polytopes by
  support functions, raising :class:`~balustrade.errors.EmptySetError` naming the set;
* :func:`is_rpi` — a numerical check (support functions, exact trust-region maxima for
  ellipsoids, and sampling) that ``A_K E ⊕ G W ⊆ E``;
* :class:`ErrorSet` — an error set with its feedback; for nonlinear systems a user-given ``E``
  and ``κ`` (designing incremental Lyapunov functions is out of scope).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from balustrade._checks import as_count, as_matrix, check_instance
from balustrade.dsl import sets_geometry as geo
from balustrade.dsl.sets import Box, Ellipsoid, Polytope, Set
from balustrade.errors import (
    BalustradeError,
    EmptySetError,
    ShapeError,
    UnprovenCheckWarning,
    moved_names,
)


# -- error sets with their feedback ------------------------------------------------------------
@dataclass(frozen=True)
class ErrorSet:
    """An RPI error set ``E`` with its error feedback ``κ(e) = K e`` (Assumption 5.13).

    ``kappa`` may be a user-given (nonlinear) callable for nonlinear systems; the input
    tightening ``U ⊖ κ(E)`` then needs ``K`` (linear κ) or a user-tightened input set.
    """

    E: Set
    K: np.ndarray | None
    kappa_fn: Callable[[np.ndarray], np.ndarray] | None = None
    info: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.E, Set):
            raise BalustradeError(f"ErrorSet: E must be a balustrade Set, got "
                                  f"{type(self.E).__name__}")
        if self.K is not None:
            object.__setattr__(self, "K", as_matrix(self.K, f"ErrorSet({self.E.name}): K",
                                                    (None, self.E.dim)))
        if self.kappa_fn is not None and not callable(self.kappa_fn):
            raise BalustradeError(f"ErrorSet({self.E.name}): kappa_fn must be callable, got "
                                  f"{type(self.kappa_fn).__name__}")

    def kappa(self, e: np.ndarray) -> np.ndarray:
        """``κ(e)``: ``K e`` or the user's feedback. ``K e`` is summed left to right from its
        first term (``K[:, 0] e_0 + K[:, 1] e_1 + …``), the order of the emitted C's applied
        input (``bal/tube_common.c``), so that C and Python round alike (BLAS may reorder or
        fuse the products of ``K @ e``)."""
        e = np.asarray(e, dtype=float).reshape(-1)
        if self.kappa_fn is not None:
            return np.asarray(self.kappa_fn(e), dtype=float).reshape(-1)
        if self.K is None:
            raise BalustradeError(f"ErrorSet({self.E.name}): no feedback K or κ given")
        K = self.K
        if e.size != K.shape[1] or e.size == 0:
            raise ShapeError(f"ErrorSet({self.E.name}).kappa: e", (K.shape[1],), e.shape)
        out = K[:, 0] * e[0]
        for j in range(1, e.size):
            out = out + K[:, j] * e[j]
        return out

    def tighten_state(self, X: Polytope, name: str | None = None) -> Polytope:
        """``X ⊖ E``."""
        return tighten(X, self.E, name=name)

    def tighten_input(self, U: Polytope, name: str | None = None) -> Polytope:
        """``U ⊖ K E`` (linear κ only)."""
        if self.K is None:
            raise BalustradeError(f"ErrorSet({self.E.name}): U ⊖ κ(E) needs a linear "
                                  "feedback K; give a tightened input set for a nonlinear κ")
        return tighten_by_feedback(U, self.K, self.E, name=name)


# -- tightening by support functions --------------------------------------------------------
def _row_support(E: Set, a: np.ndarray) -> float:
    return float(E.support(a))


def tighten(S: Polytope, E: Set, name: str | None = None) -> Polytope:
    """``S ⊖ E = {x : H x <= h − [h_E(H_jᵀ)]_j}`` (SPEC §1.5) as a :class:`Polytope`.

    Raises :class:`EmptySetError` naming ``S`` and ``E`` when the result is empty.
    """
    check_instance(E, Set, "tighten: E")
    if not isinstance(S, Polytope):
        raise BalustradeError(f"tighten: the minuend must be a Polytope or Box, got "
                              f"{type(S).__name__} {getattr(S, 'name', '')!r}")
    if E.dim != S.dim:
        raise ShapeError(f"tighten {S.name} ⊖ {E.name}", f"a set of dimension {S.dim}",
                         f"dimension {E.dim}")
    s = np.array([_row_support(E, row) for row in S.H])
    return _shifted(S, s, name or f"{S.name}⊖{E.name}", f"{S.name} by {E.name}")


def tighten_by_feedback(U: Polytope, K: np.ndarray, E: Set, name: str | None = None
                        ) -> Polytope:
    """``U ⊖ K E = {v : A_u v <= b_u − [h_E(Kᵀ [A_u]_jᵀ)]_j}`` (SPEC §1.5)."""
    check_instance(U, Polytope, "tighten_by_feedback: U")
    check_instance(E, Set, "tighten_by_feedback: E")
    K = as_matrix(K, "tighten_by_feedback: K", (U.dim, E.dim))
    s = np.array([_row_support(E, K.T @ row) for row in U.H])
    return _shifted(U, s, name or f"{U.name}⊖K{E.name}", f"{U.name} by K·{E.name}")


def tighten_rows(S: Polytope, s: np.ndarray, name: str) -> Polytope:
    """``{x : H x <= h − s}`` for given row tightenings ``s`` (e.g. reachable-set supports)."""
    s = np.asarray(s, dtype=float).reshape(-1)
    if s.size != S.H.shape[0]:
        raise ShapeError(f"tighten_rows({S.name})", (S.H.shape[0],), s.shape)
    return _shifted(S, s, name, f"{S.name} by row tightenings")


def _shifted(S: Polytope, s: np.ndarray, name: str, what: str) -> Polytope:
    if not np.all(np.isfinite(s)):
        raise EmptySetError(f"tightening {what} leaves an empty set ({name}): the error set "
                            f"is unbounded along rows {np.flatnonzero(~np.isfinite(s)).tolist()}")
    try:
        return Polytope(S.H, S.h - s, name=name)
    except EmptySetError as exc:
        raise EmptySetError(f"tightening {what} leaves an empty set ({name}); the error set "
                            f"is too large for {S.name}") from exc


# -- disturbance reachable sets E_i = ⊕_{j<i} A_K^j G W -----------------------------------------
def _disturbance(W: Set, G: np.ndarray | None, n: int) -> tuple[np.ndarray, Callable]:
    G = np.eye(n) if G is None else as_matrix(G, "disturbance matrix G", (n, W.dim))
    return G, (lambda a: W.support(G.T @ a))


def reachable_support(A_K: np.ndarray, W: Set, H: np.ndarray, N: int,
                      G: np.ndarray | None = None) -> np.ndarray:
    """``s[i, j] = h_{E_i}(H_jᵀ) = Σ_{l<i} h_W(Gᵀ (A_K^l)ᵀ H_jᵀ)`` for ``i ∈ I[0, N]``
    ((2.13), §6.3.2); ``s[0] = 0`` because ``E_0 = {0}``."""
    A_K = as_matrix(A_K, "reachable_support: A_K")
    n = A_K.shape[0]
    if A_K.shape != (n, n):
        raise ShapeError("reachable_support: A_K", "a square matrix", A_K.shape)
    N = as_count(N, "reachable_support: horizon N")
    if not isinstance(W, Set) or W.dim != (n if G is None else W.dim):
        raise ShapeError("reachable_support: W", f"a Set of dimension {n}",
                         f"{type(W).__name__} of dimension {getattr(W, 'dim', '?')}", what="")
    H = as_matrix(H, "reachable_support: H", (None, n))
    _, hW = _disturbance(W, G, n)
    s = np.zeros((N + 1, H.shape[0]))
    M = np.eye(n)  # A_K^l
    for i in range(1, N + 1):
        s[i] = s[i - 1] + np.array([hW(M.T @ a) for a in H])
        M = A_K @ M
    return s


def reachable_tightened_sets(S: Polytope, A_K: np.ndarray, W: Set, N: int,
                             G: np.ndarray | None = None, K: np.ndarray | None = None,
                             name: str | None = None) -> list[Polytope]:
    """``[S ⊖ E_0, …, S ⊖ E_N]`` (``S ⊖ K E_i`` when ``K`` is given: input sets of (2.14)/(6.10)).

    Raises :class:`EmptySetError` naming the step whose tightening empties ``S``.
    """
    check_instance(S, Polytope, "reachable_tightened_sets: S")
    H = S.H if K is None else S.H @ as_matrix(K, "reachable_tightened_sets: K",
                                                  (S.dim, None))
    s = reachable_support(A_K, W, H, N, G)
    base = name or S.name
    return [tighten_rows(S, s[i], f"{base}⊖{'K' if K is not None else ''}E_{i}")
            for i in range(N + 1)]


# -- vertices of a bounded disturbance set -------------------------------------------------------
def bounded_vertices(W: Set) -> np.ndarray:
    """The vertices of a bounded ``Box`` or ``Polytope`` ``W`` (vertex LMIs, hulls)."""
    if isinstance(W, Box):
        return W.vertices()
    if isinstance(W, Polytope):
        return W.vertices()
    raise BalustradeError(f"RPI design: W must be a bounded Box or Polytope, got "
                          f"{type(W).__name__} {W.name!r}")


# -- minimal RPI outer approximation -------------------------------------------------------------
@dataclass(frozen=True)
class MinimalRPI:
    """``F(α, s) = (1−α)⁻¹ ⊕_{i<s} A_K^i G W`` (Raković et al. 2005), RPI for ``A_K`` and
    ``ε``-close to the minimal RPI set: ``F(α, s) ⊆ F_∞ ⊕ B_∞(ε)``."""

    A_K: np.ndarray
    W: Set
    G: np.ndarray
    s: int
    alpha: float
    eps: float

    def support(self, a: np.ndarray) -> float:
        """``h_F(a) = (1−α)⁻¹ Σ_{i<s} h_W(Gᵀ (A_K^i)ᵀ a)``."""
        a = np.asarray(a, dtype=float).reshape(-1)
        total, M = 0.0, np.eye(self.A_K.shape[0])
        for _ in range(self.s):
            total += self.W.support(self.G.T @ M.T @ a)
            M = self.A_K @ M
        return total / (1.0 - self.alpha)

    def polytope(self, name: str = "F_mRPI") -> Polytope:
        """An H-representation of ``F(α, s)``: the hull of the vertex sums, pruned to the hull
        after every term (bounded ``W``, small dimensions)."""
        from scipy.spatial import ConvexHull

        from balustrade.dsl import sets_geometry as geo

        n = self.A_K.shape[0]
        Wv = bounded_vertices(self.W) @ self.G.T
        V, M = np.zeros((1, n)), np.eye(n)
        for _ in range(self.s):
            term = Wv @ M.T
            if np.max(np.abs(term)) > 1e-12 * max(1.0, float(np.max(np.abs(V)))):
                V = (V[:, None, :] + term[None, :, :]).reshape(-1, n)
                if V.shape[0] > n + 1:
                    V = V[ConvexHull(V).vertices]
            M = self.A_K @ M
        H, h = geo.hull_halfspaces(V / (1.0 - self.alpha), name)
        return Polytope(H, h, name=name)


def minimal_rpi_outer(A_K: np.ndarray, W: Polytope, eps: float = 1e-3,
                      G: np.ndarray | None = None, s_max: int = 500) -> MinimalRPI:
    """The ε-outer approximation of the minimal RPI set of ``e⁺ = A_K e + G w``, ``w ∈ W``.

    With ``α(s) = max_j h_W(Gᵀ(A_K^s)ᵀ ... )`` computed as the smallest ``α`` with
    ``A_K^s G W ⊆ α G W`` (support functions over the rows of ``W`` when ``G = I``; over a
    box enclosing ``GW`` otherwise), increase ``s`` until ``α/(1−α) · M_s <= ε`` where
    ``M_s = max_j Σ_{i<s} max(h_W(±Gᵀ(A_K^i)ᵀ e_j))`` (Raković et al. 2005, Thm. 3).
    ``W`` must contain the origin in its interior.
    """
    A_K = as_matrix(A_K, "minimal_rpi_outer: A_K")
    n = A_K.shape[0]
    if A_K.shape != (n, n):
        raise ShapeError("minimal_rpi_outer: A_K", "a square matrix", A_K.shape)
    check_instance(W, Polytope, "minimal_rpi_outer: W")
    if np.max(np.abs(np.linalg.eigvals(A_K))) >= 1:
        raise BalustradeError("minimal_rpi_outer: A_K is not Schur stable "
                              f"(spectral radius {np.max(np.abs(np.linalg.eigvals(A_K))):.4g})")
    G = np.eye(n) if G is None else as_matrix(G, "minimal_rpi_outer: G", (n, W.dim))
    # Containment A_K^s (GW) ⊆ α (GW): in the W coordinates when G = I; otherwise test against
    # the polytope GW represented by the rows of its bounding box (still an outer, RPI-valid α).
    if np.allclose(G, np.eye(n)) and isinstance(W, Polytope):
        Hc, hc = W.H, W.h
    else:
        bb = W.linear_map(G) if G.shape[0] == G.shape[1] and np.linalg.matrix_rank(G) == n \
            else None
        if bb is None:
            raise BalustradeError("minimal_rpi_outer: G must be invertible (square, full rank) "
                                  "for the α test; use the ellipsoidal RPI design instead")
        Hc, hc = bb.H, bb.h
    if np.any(hc <= 0):
        raise BalustradeError("minimal_rpi_outer: W must contain the origin in its interior")
    e = np.eye(n)
    Ms_pos, Ms_neg = np.zeros(n), np.zeros(n)
    M = np.eye(n)
    for s in range(1, s_max + 1):
        Ms_pos += np.array([W.support(G.T @ M.T @ e[j]) for j in range(n)])
        Ms_neg += np.array([W.support(-G.T @ M.T @ e[j]) for j in range(n)])
        M = A_K @ M  # A_K^s
        alpha = max(W.support(G.T @ M.T @ a) / b for a, b in zip(Hc, hc))
        if alpha < 1:
            Ms = float(max(np.max(Ms_pos), np.max(Ms_neg)))
            if alpha / (1 - alpha) * Ms <= eps:
                return MinimalRPI(A_K, W, G, s, float(alpha), float(eps))
    raise BalustradeError(f"minimal_rpi_outer: no s <= {s_max} reaches ε = {eps}")


# -- RPI check -----------------------------------------------------------------------------------
@dataclass
class RPICheck:
    """Result of :func:`is_rpi`: ``margin`` is ``max c_E(A_K e + G w)`` found (``<= tol`` ⇒ ok).
    ``proven``: whether the verdict is proven — an exact method ran, or a counterexample
    was found; ``False`` for an ``ok`` from sampling alone (then ``method`` says why, and
    :func:`is_rpi` warned with :class:`~balustrade.errors.UnprovenCheckWarning`)."""

    ok: bool
    margin: float
    method: str
    worst: dict = field(default_factory=dict)
    proven: bool = True

    def __bool__(self) -> bool:
        return self.ok


def is_rpi(E: Set, A_cl: np.ndarray, W: Set, G: np.ndarray | None = None, tol: float = 1e-7,
           samples: int = 2000, rng: int | np.random.Generator | None = 0) -> RPICheck:
    """Check ``A_cl E ⊕ G W ⊆ E`` (Assumption 5.13 for ``κ(e) = Ke``, ``A_cl = A + BK``).

    * Polytope ``E``: exact, ``h_E(A_clᵀ H_j) + h_W(Gᵀ H_j) <= h_j`` for every row.
    * Ellipsoid ``E``: exact per vertex of a polytope ``W`` (trust-region maximum of ``c_E``
      over the ellipsoid ``A_cl E + G w^v``, possibly degenerate: any ``A_cl``; ``c_E`` is
      convex so vertices suffice), plus support functions along sampled directions and
      sampled points ``e ∈ ∂E``, ``w ∈ W`` (a necessary-condition search that finds
      counterexamples; the only check for a ``W`` that is not a polytope).
    Returns an :class:`RPICheck` whose ``margin`` is in units of ``c_E``.
    """
    check_instance(E, Set, "is_rpi: E")
    check_instance(W, Set, "is_rpi: W")
    A_cl = as_matrix(A_cl, "is_rpi: A_cl", (E.dim, E.dim))
    n = E.dim
    G = np.eye(n) if G is None else as_matrix(G, "is_rpi: G", (n, W.dim))
    if G.shape[1] != W.dim:
        raise ShapeError(f"is_rpi: W ({W.name})", f"dimension {G.shape[1]}",
                         f"dimension {W.dim}")
    g = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    if isinstance(E, Polytope):
        margins = [E.support(A_cl.T @ a) + W.support(G.T @ a) - b for a, b in zip(E.H, E.h)]
        j = int(np.argmax(margins))
        return RPICheck(bool(margins[j] <= tol), float(margins[j]), "support functions (exact)",
                        {"row": j})
    if not isinstance(E, Ellipsoid):
        raise BalustradeError(f"is_rpi: E must be a Polytope or an Ellipsoid, got "
                              f"{type(E).__name__} {E.name!r}")
    worst: dict = {}
    margin, methods = -np.inf, []
    exact = isinstance(W, Polytope)
    if exact:
        # A_cl E + G w = {A_cl c + G w + A_cl L u : ||u|| <= 1} (E = c + L·ball): the maximum
        # of c_E over it is a trust-region subproblem in u, exact for any A_cl — a singular
        # A_cl (an ellipsoid image of lower dimension) included; sampling alone under-estimates
        # the maximum and once accepted a set missing RPI by 1e-4 (audit E, session 15)
        M = A_cl @ E._root()
        G_u = M.T @ E.P @ M
        for w in W.vertices():
            d = A_cl @ E.center + G @ w - E.center
            val = geo.max_convex_quadratic_on_ball(G_u, M.T @ E.P @ d, float(d @ E.P @ d)) - 1.0
            if val > margin:
                margin, worst = val, {"w": G @ w, "method": "vertex trust region"}
        methods.append("vertex trust-region (exact)")
    # support functions along random directions: h_E(A_clᵀa) + h_W(Gᵀa) <= h_E(a)
    dirs = g.standard_normal((samples, n))
    for a in dirs:
        gap = E.support(A_cl.T @ a) + W.support(G.T @ a) - E.support(a)
        # convert a support gap into c_E units (≈ 2·gap/h_E(a) for small gaps)
        val = 2.0 * gap / max(E.support(a), 1e-300)
        if val > margin:
            margin, worst = val, {"direction": a, "method": "support"}
    # sampled points on the boundary of E and in W
    pts = E.sample(samples, g)
    pts = pts / np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", pts, E.P, pts), 1e-300))[:, None]
    Ws = W.sample(samples, g) if hasattr(W, "sample") else np.zeros((samples, W.dim))
    nxt = pts @ A_cl.T + Ws @ G.T
    vals = np.einsum("ij,jk,ik->i", nxt, E.P, nxt) - 1.0
    k = int(np.argmax(vals))
    if vals[k] > margin:
        margin, worst = float(vals[k]), {"e": pts[k], "w": Ws[k], "method": "sampling"}
    methods += ["support directions", "sampling"]
    ok = bool(margin <= tol)
    if ok and not exact:
        why = f"W ({W.name}) is not a polytope"
        methods.append(f"no proof: {why}, so only sampled directions and points were checked")
        warnings.warn(f"is_rpi: {E.name} passed a search for counterexamples only, not a "
                      f"proof ({why}; the exact vertex trust-region check needs a "
                      "polytope W)", UnprovenCheckWarning, stacklevel=2)
    return RPICheck(ok, float(margin), ", ".join(methods), worst, proven=not ok or exact)

#: names that moved out of this module (issue #13): deprecated aliases (errors.moved_names)
__getattr__ = moved_names(__name__, {
    "ellipsoidal_rpi": "balustrade.design.rpi",
})
