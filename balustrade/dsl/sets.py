"""Sets used as constraints, disturbance bounds, error sets and terminal sets.

Every set is written as ``{x : c(x) <= 0}`` (SPEC §1.3) so that the horizon problem builder
can impose ``x ∈ S`` (hard), ``c(x) <= ξ`` (soft, slack ξ) or ``c(x) + Δ_i <= ξ``
(tightened, SPEC §1.4) for any set, whatever its kind:

* :class:`Polytope` ``{x : H x <= h}`` with ``c(x) = H x - h`` (rows not normalised, SPEC §1.3),
* :class:`Box` ``{lb <= x <= ub}`` (a polytope with ``H = [I; -I]``),
* :class:`Ellipsoid` ``{x : (x - q)ᵀ P (x - q) <= 1}`` with ``c(x) = (x - q)ᵀ P (x - q) - 1``,
* :class:`FunctionSet` ``{x : c(x) <= 0}`` for any CasADi-callable ``c``.

Tightening uses support functions only (SPEC §1.5): ``{Hx <= h} ⊖ B = {Hx <= h - [h_B(H_jᵀ)]_j}``.

Set operations (SPEC §1.5, §1.11), with the result type and whether it is exact:

* ``S.support(a)``: ``h_S(a) = max_{x∈S} aᵀx`` by LP or closed form (``+inf`` if unbounded).
* ``S.linear_map(A)``, ``A @ S``, ``linear_map(A, S)``: exact. Ellipsoid for ``A`` of full row
  rank; Polytope/Box ``{H A⁻¹ y <= h}`` for invertible ``A``, otherwise the hull of the
  mapped vertices (bounded polytopes, dimension <= 6); FunctionSet for invertible ``A``.
* ``S.minkowski_sum(T)``: exact for Box ⊕ Box and Polytope ⊕ Polytope (bounded, by
  vertices); an **outer approximation** for Ellipsoid ⊕ Ellipsoid (minimum-trace ellipsoid)
  and Polytope ⊕ Ellipsoid (same normals, ``h_j + h_E(H_jᵀ)``).
* ``P.tighten(B)`` = ``P.pontryagin_difference(B)``: exact ``P ⊖ B`` for any ``B``.
* ``S.is_subset_of(T)``: exact for any set ⊆ Polytope (support functions), Ellipsoid ⊆
  Ellipsoid (trust-region subproblem), bounded Polytope ⊆ Ellipsoid (vertices).
* ``S.sample(n, rng)``: uniform; exact for Box and Ellipsoid, rejection from the bounding
  box for polytopes (hit-and-run when the acceptance rate is tiny), rejection from
  user-given bounds for a FunctionSet.
* ``bounding_box``, ``chebyshev_center``, ``vertices``, ``is_bounded``, ``scale``,
  ``translate``, ``contains_many``.

The base class is in :mod:`balustrade.dsl.sets_base`, :class:`FunctionSet` in
:mod:`balustrade.dsl.sets_function`, binary operations in :mod:`balustrade.dsl.sets_ops` and
the array-level algorithms in :mod:`balustrade.dsl.sets_geometry`; import from here.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from balustrade._checks import as_count, as_matrix, as_vector, check_name, check_psd
from balustrade.dsl import sets_geometry as geo
from balustrade.dsl import sets_project
from balustrade.dsl.sets_base import (
    RngLike,
    Set,
    Symbolic,
    as_rng,
    check_count,
    check_scalar,
    check_tol,
    linear_map,
    minkowski_sum,
    pontryagin_difference,
)
from balustrade.dsl.sets_function import FunctionSet
from balustrade.errors import BalustradeError, EmptySetError, NonFiniteError, ShapeError

__all__ = [
    "Box",
    "Ellipsoid",
    "FunctionSet",
    "Polytope",
    "RngLike",
    "Set",
    "Symbolic",
    "as_rng",
    "linear_map",
    "minkowski_sum",
    "pontryagin_difference",
]


@dataclass(frozen=True, eq=False)
class Polytope(Set):
    """H-polytope ``{x : H x <= h}`` (SPEC §1.3, polytopic form)."""

    H: np.ndarray
    h: np.ndarray
    name: str = "Polytope"

    def __post_init__(self) -> None:
        check_name(self.name, "Polytope: name")
        H = as_matrix(self.H, f"{self.name}: H")
        if H.shape[1] == 0:
            raise ShapeError(f"{self.name}: H", "at least one column (the set's dimension)",
                             H.shape)
        h = as_vector(self.h, f"{self.name}: h")
        if H.shape[0] != h.size:
            raise ShapeError(f"{self.name}: h must have one entry per row of H",
                             (H.shape[0],), h.shape)
        object.__setattr__(self, "H", H)
        object.__setattr__(self, "h", h)
        if self.is_empty():
            raise EmptySetError(f"{self.name}: polytope {{Hx <= h}} with H of shape {H.shape} "
                                "is empty")

    @property
    def dim(self) -> int:  # type: ignore[override]
        return int(self.H.shape[1])

    def c(self, x: Symbolic) -> Symbolic:
        self._check_point_dim(x, "c(x)")
        return ca.mtimes(ca.DM(self.H), x) - ca.DM(self.h)

    @property
    def n_rows(self) -> int:
        """Number of rows of ``H`` (counted, not by building the CasADi expression ``c``)."""
        return int(self.H.shape[0])

    def contains(self, x: np.ndarray, tol: float = 1e-9) -> bool:
        """``Hx − h <= tol`` row-wise, with NumPy (the filters call it every step)."""
        x = as_vector(x, f"{self.name}.contains(x)", self.dim)
        tol = check_tol(tol, f"{self.name}.contains")
        return bool(np.all(self.H @ x - self.h <= tol))

    def contains_many(self, X: np.ndarray, tol: float = 1e-9) -> np.ndarray:
        X = self._points(X, "contains_many(X)")
        tol = check_tol(tol, f"{self.name}.contains_many")
        return np.all(X @ self.H.T - self.h <= tol, axis=1)

    def _project(self, x: np.ndarray) -> np.ndarray:
        return sets_project.project_polytope(x, self.H, self.h, self.name)

    def is_empty(self) -> bool:
        """Whether ``{Hx <= h}`` is empty (one LP)."""
        res = geo.linprog(np.zeros(self.dim), self.H, self.h, [(None, None)] * self.dim)
        return res.status == 2

    def support(self, a: np.ndarray) -> float:
        """``max_{x∈P} aᵀx`` as a verified upper bound (session 13, audit finding 5): the
        LP's multipliers bound it by weak duality (:func:`~balustrade.dsl.sets_geometry.
        verified_upper`) over a box that provably contains ``P`` (:meth:`verified_box`),
        so a solver tolerance can only raise the value, never lower it (the LP optimum
        alone was up to 2.8e-7 below the exact support of the 8-mass 𝕏₀, and the tube
        constants s_jr, t_r of SPEC §2.20 are such supports). ``+inf`` along an unbounded
        direction; an unbounded polytope has no such box and gets the LP optimum."""
        a = as_vector(a, f"{self.name}.support(a)", self.dim)
        res = geo.linprog(-a, self.H, self.h, [(None, None)] * self.dim)
        if res.status == 3:
            return float("inf")
        if res.status != 0:
            raise BalustradeError(f"{self.name}.support: LP failed ({res.message})")
        box = self.verified_box()
        if box is None:
            return float(-res.fun)
        y = -np.asarray(res.ineqlin.marginals, dtype=float)
        return max(float(-res.fun), geo.verified_upper(a, self.H, self.h, *box, y))

    def verified_box(self) -> tuple[np.ndarray, np.ndarray] | None:
        """A box that provably contains the polytope (:func:`~balustrade.dsl.
        sets_geometry.verified_box`, ``2·dim`` LPs, computed once per polytope), or
        ``None`` when it is unbounded."""
        if "_verified_box" not in self.__dict__:
            object.__setattr__(self, "_verified_box", geo.verified_box(self.H, self.h))
        return self.__dict__["_verified_box"]

    def tighten(self, other: Set, name: str | None = None) -> Polytope:
        """Pontryagin difference ``self ⊖ other`` by support functions (SPEC §1.5).

        Raises :class:`EmptySetError` naming both sets when the result is empty, including
        when ``other`` is unbounded along a row normal.
        """
        self._check_same_dim(other, "⊖")
        s = np.array([other.support(row) for row in self.H])
        new_name = name or f"{self.name}⊖{other.name}"
        if not np.all(np.isfinite(s)):
            raise EmptySetError(f"tightening {self.name} by {other.name} leaves an empty set "
                                f"({new_name}): {other.name} is unbounded along rows "
                                f"{np.flatnonzero(~np.isfinite(s)).tolist()} of H")
        h_new = self.h - s
        try:
            return Polytope(self.H, h_new, name=new_name)
        except EmptySetError as exc:
            raise EmptySetError(f"tightening {self.name} by {other.name} leaves an empty set "
                                f"({new_name})") from exc

    def pontryagin_difference(self, other: Set, name: str | None = None) -> Polytope:
        """Alias of :meth:`tighten` (SPEC §1.5)."""
        return self.tighten(other, name=name)

    # -- geometry ---------------------------------------------------------------------------
    def bounding_box(self) -> Box:
        """Smallest enclosing box by ``2·dim`` LPs (infinite bounds where unbounded)."""
        lb, ub = geo.bounding_box(self.H, self.h, self.name)
        return Box(lb, ub, name=f"bbox({self.name})")

    def chebyshev_center(self) -> tuple[np.ndarray, float]:
        """Centre and radius of the largest inscribed Euclidean ball (one LP)."""
        return geo.chebyshev_center(self.H, self.h, self.name)

    def vertices(self) -> np.ndarray:
        """Vertices (rows) of a bounded polytope of dimension <= 6 (HalfspaceIntersection
        from the Chebyshev centre; flat polytopes are handled on their affine hull)."""
        return geo.vertices(self.H, self.h, self.name)

    def _require_bounded(self, op: str) -> None:
        if not self.is_bounded():
            raise BalustradeError(f"{self.name}.{op}: needs a bounded set, but this polytope "
                                  f"(H of shape {self.H.shape}) is unbounded")

    # -- operations -------------------------------------------------------------------------
    def linear_map(self, A: np.ndarray, name: str | None = None) -> Polytope:
        """``A·P``: ``{y : H A⁻¹ y <= h}`` for invertible square ``A``; otherwise the convex
        hull of the mapped vertices (bounded polytopes, dimension <= 6)."""
        A = self._map_matrix(A)
        new_name = name or f"A·{self.name}"
        m, n = A.shape
        if m == n and np.linalg.matrix_rank(A) == n:
            return Polytope(np.linalg.solve(A.T, self.H.T).T, self.h, name=new_name)
        if max(m, n) > geo.MAX_VERTEX_DIM:
            raise BalustradeError(f"{self.name}.linear_map: A of shape {A.shape} is not "
                                  "invertible, and images by vertices are limited to "
                                  f"dimension <= {geo.MAX_VERTEX_DIM}")
        if not self.is_bounded():
            raise BalustradeError(f"{self.name}.linear_map: A of shape {A.shape} is not "
                                  f"invertible and the polytope (dimension {n}) is unbounded; "
                                  "the image needs a bounded polytope")
        Hm, hm = geo.hull_halfspaces(self.vertices() @ A.T, f"{self.name}.linear_map")
        return Polytope(Hm, hm, name=new_name)

    def scale(self, alpha: float, name: str | None = None) -> Polytope:
        a = check_scalar(alpha, f"{self.name}.scale")
        new_name = name or f"{a:g}·{self.name}"
        if a == 0.0:
            return Box(np.zeros(self.dim), np.zeros(self.dim), name=new_name)
        return Polytope(np.sign(a) * self.H, abs(a) * self.h, name=new_name)

    def translate(self, v: np.ndarray, name: str | None = None) -> Polytope:
        v = as_vector(v, f"{self.name}.translate(v)", self.dim)
        return Polytope(self.H, self.h + self.H @ v, name=name or f"{self.name}+v")

    def sample(self, n: int, rng: RngLike = None, method: str = "auto") -> np.ndarray:
        """Uniform samples of a bounded polytope: rejection from the bounding box, falling back
        to hit-and-run when the acceptance rate is below 1e-3 (``method`` forces one)."""
        n = check_count(n, f"{self.name}.sample")
        return geo.sample_polytope(self.H, self.h, n, as_rng(rng), f"{self.name}.sample",
                                   method=method)


class Box(Polytope):
    """Axis-aligned box ``{lb <= x <= ub}``; ``c(x) = [x - ub; lb - x]`` (rows with an infinite
    bound are left out)."""

    def __init__(self, lb: np.ndarray, ub: np.ndarray, name: str = "Box"):
        check_name(name, "Box: name")
        lb = as_vector(lb, f"{name}: lb", finite=False)
        if lb.size == 0:
            raise ShapeError(f"{name}: lb", "at least one bound (a box of dimension >= 1)",
                             lb.shape)
        ub = as_vector(ub, f"{name}: ub", lb.size, finite=False)
        if np.any(np.isnan(lb)) or np.any(np.isnan(ub)):
            raise NonFiniteError(f"{name}: bounds contain NaN (lb={lb}, ub={ub})")
        bad = (lb > ub) | (lb == np.inf) | (ub == -np.inf)
        if np.any(bad):
            raise EmptySetError(f"{name}: lower bound exceeds upper bound (or a bound is +inf "
                                f"below / -inf above) at indices {np.flatnonzero(bad).tolist()}")
        keep_u = np.isfinite(ub)
        keep_l = np.isfinite(lb)
        n = lb.size
        H = np.vstack([np.eye(n)[keep_u], -np.eye(n)[keep_l]])
        h = np.concatenate([ub[keep_u], -lb[keep_l]])
        object.__setattr__(self, "lb", lb)
        object.__setattr__(self, "ub", ub)
        object.__setattr__(self, "_n", n)
        super().__init__(H.reshape(-1, n), h, name=name)

    def __repr__(self) -> str:
        lb, ub = getattr(self, "lb", None), getattr(self, "ub", None)
        if lb is None or ub is None:  # during construction
            return f"Box(<incomplete>, name={getattr(self, 'name', None)!r})"
        return f"Box(lb={lb.tolist()}, ub={ub.tolist()}, name={self.name!r})"

    @classmethod
    def symmetric(cls, bound: np.ndarray | float, dim: int | None = None,
                  name: str = "Box") -> Box:
        """``{|x_i| <= bound_i}`` (``bound >= 0``; ``inf`` for no bound)."""
        b = as_vector(bound, f"{name}: bound", finite=False)
        if dim is not None:
            dim = as_count(dim, f"{name}: dim", low=1)
            if b.size == 1:
                b = np.full(dim, float(b[0]))
            elif b.size != dim:
                raise ShapeError(f"{name}: bound", (dim,), b.shape)
        if np.any(b < 0):
            raise EmptySetError(f"{name}: symmetric bound {b} has negative entries "
                                f"{np.flatnonzero(b < 0).tolist()}: the box is empty")
        return cls(-b, b, name=name)

    @property
    def dim(self) -> int:  # type: ignore[override]
        return int(self._n)

    def _project(self, x: np.ndarray) -> np.ndarray:
        return sets_project.project_box(x, self.lb, self.ub)

    def support(self, a: np.ndarray) -> float:
        """``Σ_i max(a_i ub_i, a_i lb_i)``; ``+inf`` where ``a_i`` points to an infinite bound."""
        a = as_vector(a, f"{self.name}.support(a)", self.dim)
        vals = np.zeros(self.dim)
        pos, neg = a > 0, a < 0
        vals[pos] = a[pos] * self.ub[pos]
        vals[neg] = a[neg] * self.lb[neg]
        return float(np.sum(vals))

    def vertices(self) -> np.ndarray:
        """All ``2^dim`` vertices (rows)."""
        if not (np.all(np.isfinite(self.lb)) and np.all(np.isfinite(self.ub))):
            raise BalustradeError(f"{self.name}: unbounded box has no vertices")
        pairs = [[lo, hi] for lo, hi in zip(self.lb, self.ub, strict=True)]
        grids = np.meshgrid(*pairs, indexing="ij")
        return np.stack([g.ravel() for g in grids], axis=1)

    def bounding_box(self) -> Box:
        return self

    def is_empty(self) -> bool:
        """Never: the constructor refuses ``lb > ub`` (no LP, unlike a general polytope)."""
        return False

    def is_bounded(self) -> bool:
        return bool(np.all(np.isfinite(self.lb)) and np.all(np.isfinite(self.ub)))

    def chebyshev_center(self) -> tuple[np.ndarray, float]:
        if self.is_bounded():
            return 0.5 * (self.lb + self.ub), float(np.min(0.5 * (self.ub - self.lb)))
        return super().chebyshev_center()

    def tighten(self, other: Set, name: str | None = None) -> Box:
        """``Box ⊖ B`` is the box ``[lb + h_B(-e_i), ub - h_B(e_i)]`` (SPEC §1.5); same rows
        ``H, h`` as :meth:`Polytope.tighten`."""
        self._check_same_dim(other, "⊖")
        new_name = name or f"{self.name}⊖{other.name}"
        e = np.eye(self.dim)
        ub, lb = self.ub.copy(), self.lb.copy()
        for i in range(self.dim):
            if np.isfinite(ub[i]):
                ub[i] -= other.support(e[i])
            if np.isfinite(lb[i]):
                lb[i] += other.support(-e[i])
        if np.any(np.isnan(ub)) or np.any(np.isnan(lb)) or np.any(ub == -np.inf) or np.any(
                lb == np.inf):
            raise EmptySetError(f"tightening {self.name} by {other.name} leaves an empty set "
                                f"({new_name}): {other.name} is unbounded")
        try:
            return Box(lb, ub, name=new_name)
        except EmptySetError as exc:
            raise EmptySetError(f"tightening {self.name} by {other.name} leaves an empty set "
                                f"({new_name})") from exc

    def linear_map(self, A: np.ndarray, name: str | None = None) -> Polytope:
        """As :meth:`Polytope.linear_map`; a nonsingular diagonal ``A`` gives a :class:`Box`."""
        A = self._map_matrix(A)
        d = np.diag(A) if A.shape[0] == A.shape[1] else None
        if d is not None and np.all(A == np.diag(d)) and np.all(d != 0):
            return self._scaled(d, name or f"A·{self.name}")
        return super().linear_map(A, name=name)

    def _scaled(self, d: np.ndarray, name: str) -> Box:
        with np.errstate(invalid="ignore"):
            lo, hi = d * self.lb, d * self.ub
        lo = np.where(d == 0, 0.0, lo)
        hi = np.where(d == 0, 0.0, hi)
        return Box(np.minimum(lo, hi), np.maximum(lo, hi), name=name)

    def scale(self, alpha: float, name: str | None = None) -> Box:
        a = check_scalar(alpha, f"{self.name}.scale")
        return self._scaled(np.full(self.dim, a), name or f"{a:g}·{self.name}")

    def translate(self, v: np.ndarray, name: str | None = None) -> Box:
        v = as_vector(v, f"{self.name}.translate(v)", self.dim)
        return Box(self.lb + v, self.ub + v, name=name or f"{self.name}+v")

    def sample(self, n: int, rng: RngLike = None, method: str = "auto") -> np.ndarray:
        """Exact uniform samples (``method`` is ignored: boxes need no rejection)."""
        n = check_count(n, f"{self.name}.sample")
        if not self.is_bounded():
            raise BalustradeError(f"{self.name}.sample: cannot sample an unbounded box "
                                  f"(lb={self.lb}, ub={self.ub})")
        with np.errstate(over="ignore"):
            width = self.ub - self.lb
        if not np.all(np.isfinite(width)):
            raise BalustradeError(f"{self.name}.sample: the box is too wide to sample in "
                                  f"floating point (ub - lb overflows: lb={self.lb}, "
                                  f"ub={self.ub})")
        return as_rng(rng).uniform(self.lb, self.ub, size=(n, self.dim))


@dataclass(frozen=True, eq=False)
class Ellipsoid(Set):
    """``{x : (x - center)ᵀ P (x - center) <= 1}`` with ``P ≻ 0``."""

    P: np.ndarray
    center: np.ndarray | None = None
    name: str = "Ellipsoid"

    def __post_init__(self) -> None:
        check_name(self.name, "Ellipsoid: name")
        P = check_psd(self.P, f"{self.name}: P", strict=True)
        q = np.zeros(P.shape[0]) if self.center is None else as_vector(
            self.center, f"{self.name}: center", P.shape[0])
        object.__setattr__(self, "P", P)
        object.__setattr__(self, "center", q)

    @property
    def dim(self) -> int:  # type: ignore[override]
        return int(self.P.shape[0])

    @property
    def shape_matrix(self) -> np.ndarray:
        """``P⁻¹`` (the ellipsoid is ``center + P^{-1/2}·unit ball``)."""
        return np.linalg.inv(self.P)

    def _root(self) -> np.ndarray:
        """``L`` with ``L Lᵀ = P⁻¹``: the ellipsoid is ``center + L·(unit ball)``."""
        R = np.linalg.cholesky(self.P)  # P = R Rᵀ
        return np.linalg.solve(R.T, np.eye(self.dim))

    def c(self, x: Symbolic) -> Symbolic:
        self._check_point_dim(x, "c(x)")
        d = x - ca.DM(self.center)
        return ca.mtimes([d.T, ca.DM(self.P), d]) - 1

    def contains_many(self, X: np.ndarray, tol: float = 1e-9) -> np.ndarray:
        D = self._points(X, "contains_many(X)") - self.center
        tol = check_tol(tol, f"{self.name}.contains_many")
        return np.einsum("ij,jk,ik->i", D, self.P, D) - 1.0 <= tol

    def _project(self, x: np.ndarray) -> np.ndarray:
        return sets_project.project_ellipsoid(x, self.P, self.center)

    def support(self, a: np.ndarray) -> float:
        """``h(a) = aᵀq + sqrt(aᵀ P⁻¹ a)`` (SPEC §1.4)."""
        a = as_vector(a, f"{self.name}.support(a)", self.dim)
        return float(a @ self.center + np.sqrt(max(a @ np.linalg.solve(self.P, a), 0.0)))

    def bounding_box(self) -> Box:
        """``center ± sqrt(diag(P⁻¹))``."""
        r = np.sqrt(np.maximum(np.diag(self.shape_matrix), 0.0))
        return Box(self.center - r, self.center + r, name=f"bbox({self.name})")

    def is_bounded(self) -> bool:
        return True

    def chebyshev_center(self) -> tuple[np.ndarray, float]:
        """``(center, 1/sqrt(λ_max(P)))``."""
        return self.center.copy(), float(1.0 / np.sqrt(np.max(np.linalg.eigvalsh(self.P))))

    def linear_map(self, A: np.ndarray, name: str | None = None) -> Ellipsoid:
        """``A·E`` for ``A`` of full row rank: shape matrix ``A P⁻¹ Aᵀ``, centre ``A q``
        (``P' = A⁻ᵀ P A⁻¹`` when ``A`` is square)."""
        A = self._map_matrix(A)
        m, n = A.shape
        new_name = name or f"A·{self.name}"
        if m > n or np.linalg.matrix_rank(A) < m:
            raise BalustradeError(f"{self.name}.linear_map: A of shape {A.shape} (rank "
                                  f"{np.linalg.matrix_rank(A)}) maps the ellipsoid of "
                                  f"dimension {n} to a degenerate ellipsoid; A needs full "
                                  "row rank")
        if m == n:
            Ainv = np.linalg.inv(A)
            Pn = Ainv.T @ self.P @ Ainv
        else:
            Pn = np.linalg.inv(A @ self.shape_matrix @ A.T)
        return Ellipsoid(0.5 * (Pn + Pn.T), A @ self.center, name=new_name)

    def scale(self, alpha: float, name: str | None = None) -> Ellipsoid:
        a = check_scalar(alpha, f"{self.name}.scale")
        if a == 0.0:
            raise BalustradeError(f"{self.name}.scale: 0·{self.name} is a point, not an "
                                  "ellipsoid with P ≻ 0")
        with np.errstate(over="ignore", under="ignore"):
            P = self.P / np.float64(a) ** 2
        return Ellipsoid(P, a * self.center, name=name or f"{a:g}·{self.name}")

    def translate(self, v: np.ndarray, name: str | None = None) -> Ellipsoid:
        v = as_vector(v, f"{self.name}.translate(v)", self.dim)
        return Ellipsoid(self.P, self.center + v, name=name or f"{self.name}+v")

    def sample(self, n: int, rng: RngLike = None) -> np.ndarray:
        """Exact uniform samples: uniform direction × ``U^{1/dim}`` radius, mapped by ``L``."""
        n = check_count(n, f"{self.name}.sample")
        g = as_rng(rng)
        u = g.standard_normal((n, self.dim))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        r = g.uniform(size=(n, 1)) ** (1.0 / self.dim)
        return self.center + (r * u) @ self._root().T

    def max_quadratic_over(self, other: Ellipsoid) -> float:
        """``max_{x ∈ other} (x - q)ᵀP(x - q)`` exactly (trust-region subproblem)."""
        if not isinstance(other, Ellipsoid):
            raise BalustradeError(f"{self.name}.max_quadratic_over: expected an Ellipsoid, got "
                                  f"{type(other).__name__}")
        self._check_same_dim(other, "max_quadratic_over")
        L = other._root()
        d = other.center - self.center
        G = L.T @ self.P @ L
        return geo.max_convex_quadratic_on_ball(G, L.T @ self.P @ d, float(d @ self.P @ d))
