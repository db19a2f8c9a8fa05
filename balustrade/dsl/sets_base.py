"""Base class :class:`Set` of all sets ``{x : c(x) <= 0}`` (SPEC §1.3) and shared helpers.

The concrete sets live in :mod:`balustrade.dsl.sets` (Polytope, Box, Ellipsoid) and
:mod:`balustrade.dsl.sets_function` (FunctionSet); binary operations in
:mod:`balustrade.dsl.sets_ops`. Import everything from :mod:`balustrade.dsl.sets`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import TYPE_CHECKING

import casadi as ca
import numpy as np

from balustrade._checks import as_matrix, as_scalar, as_vector
from balustrade.errors import BalustradeError, ShapeError

if TYPE_CHECKING:
    from balustrade.dsl.sets import Box

Symbolic = ca.SX | ca.MX | ca.DM
RngLike = int | np.random.Generator | None
MAX_SAMPLES = 10**8


def as_rng(rng: RngLike) -> np.random.Generator:
    """A numpy ``Generator`` from an int seed, a ``Generator`` or ``None`` (fresh entropy)."""
    if isinstance(rng, np.random.Generator):
        return rng
    if rng is None or (isinstance(rng, (int, np.integer)) and not isinstance(rng, bool)
                       and rng >= 0):
        return np.random.default_rng(rng)
    raise BalustradeError(f"rng must be an int seed >= 0 or a numpy Generator, got "
                          f"{type(rng).__name__} {rng!r:.30}")


def check_count(n: int, block: str) -> int:
    """Validate a sample count."""
    if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 0:
        raise BalustradeError(f"{block}: the number of samples must be an int >= 0, got {n!r}")
    if n > MAX_SAMPLES:
        raise BalustradeError(f"{block}: {n} samples requested, at most {MAX_SAMPLES:.0e} per "
                              "call (draw them in batches)")
    return int(n)


def check_tol(tol: float, block: str) -> float:
    """A finite tolerance (membership, inclusion)."""
    return as_scalar(tol, f"{block}: tol")


def check_scalar(alpha: float, block: str) -> float:
    """Validate a finite scale factor."""
    return as_scalar(alpha, f"{block}: scale factor")


class Set(ABC):
    """A closed set ``{x ∈ R^dim : c(x) <= 0}``."""

    dim: int
    name: str
    #: make ``ndarray @ S`` call :meth:`__rmatmul__` instead of numpy broadcasting
    __array_ufunc__ = None

    @abstractmethod
    def c(self, x: Symbolic) -> Symbolic:
        """Constraint function rows ``c(x)`` (a column), ``x ∈ S ⟺ c(x) <= 0``."""

    @property
    def n_rows(self) -> int:
        """Number of rows of ``c``."""
        return int(self.c(ca.SX.sym("x", self.dim)).numel())

    @abstractmethod
    def support(self, a: np.ndarray) -> float:
        """Support function ``h_S(a) = max_{x∈S} aᵀx``."""

    def contains(self, x: np.ndarray, tol: float = 1e-9) -> bool:
        """Whether the point ``x`` lies in the set (up to ``tol``)."""
        x = as_vector(x, f"{self.name}.contains(x)", self.dim)
        tol = check_tol(tol, f"{self.name}.contains")
        return bool(np.all(np.asarray(ca.evalf(self.c(ca.DM(x)))).ravel() <= tol))

    def contains_many(self, X: np.ndarray, tol: float = 1e-9) -> np.ndarray:
        """Row-wise :meth:`contains` for the points ``X`` of shape ``(n, dim)`` (bool array)."""
        X = self._points(X, "contains_many(X)")
        tol = check_tol(tol, f"{self.name}.contains_many")
        if X.shape[0] == 0:
            return np.zeros(0, dtype=bool)
        x = ca.SX.sym("x", self.dim)
        fun = ca.Function("c", [x], [self.c(x)]).map(X.shape[0])
        vals = np.asarray(fun(ca.DM(X.T))).reshape(-1, X.shape[0])
        return np.all(vals <= tol, axis=0)

    def _points(self, X: np.ndarray, what: str) -> np.ndarray:
        X = as_matrix(X, f"{self.name}.{what}", finite=False) if np.ndim(X) != 1 \
            else as_vector(X, f"{self.name}.{what}", finite=False)
        if X.ndim == 1 and self.dim == 1:
            X = X[:, None]
        if X.ndim != 2 or X.shape[1] != self.dim:
            raise ShapeError(f"{self.name}.{what}", f"(n, {self.dim})", X.shape)
        return X

    def _check_point_dim(self, x: Symbolic, block: str) -> None:
        if not isinstance(x, (ca.SX, ca.MX, ca.DM)):
            raise BalustradeError(f"{block} of {self.name}: expected a CasADi column of shape "
                                  f"({self.dim}, 1), got {type(x).__name__} (use contains() "
                                  "for numeric points)")
        if x.shape != (self.dim, 1):
            raise ShapeError(f"{block} of {self.name}", (self.dim, 1), x.shape)

    def _check_same_dim(self, other: Set, op: str) -> None:
        if not isinstance(other, Set):
            raise BalustradeError(f"{self.name} {op} ...: expected a balustrade Set, "
                                  f"got {type(other).__name__}")
        if other.dim != self.dim:
            raise ShapeError(f"{self.name} {op} {other.name}", f"a set of dimension {self.dim}",
                             f"dimension {other.dim}")

    def _map_matrix(self, A: np.ndarray) -> np.ndarray:
        block = f"{self.name}.linear_map(A)"
        A = as_matrix(A, block)
        if A.shape[1] != self.dim:
            raise ShapeError(block, f"(m, {self.dim})", A.shape)
        return A

    # -- derived quantities -----------------------------------------------------------------
    def bounding_box(self) -> Box:
        """Smallest axis-aligned box containing the set (``2·dim`` support evaluations)."""
        e = np.eye(self.dim)
        ub = np.array([self.support(e[i]) for i in range(self.dim)])
        lb = np.array([-self.support(-e[i]) for i in range(self.dim)])
        from balustrade.dsl.sets import Box

        return Box(lb, ub, name=f"bbox({self.name})")

    def is_bounded(self) -> bool:
        """Whether the set is bounded (its bounding box is finite)."""
        bb = self.bounding_box()
        return bool(np.all(np.isfinite(bb.lb)) and np.all(np.isfinite(bb.ub)))

    # -- operations (overridden where a closed form exists) -----------------------------------
    def linear_map(self, A: np.ndarray, name: str | None = None) -> Set:
        """Image ``A·S = {Ax : x ∈ S}`` (SPEC §1.5, ``κ(E)`` for ``κ(e) = Ke``)."""
        A = self._map_matrix(A)
        raise BalustradeError(f"{self.name}.linear_map: no representation of the image of a "
                              f"{type(self).__name__} of dimension {self.dim} under A of "
                              f"shape {A.shape}")

    def __rmatmul__(self, A: np.ndarray) -> Set:
        return self.linear_map(A)

    def scale(self, alpha: float, name: str | None = None) -> Set:
        """``αS = {αx : x ∈ S}`` (SPEC §1.5)."""
        raise BalustradeError(f"{self.name}.scale: not available for {type(self).__name__}")

    def translate(self, v: np.ndarray, name: str | None = None) -> Set:
        """``S + v = {x + v : x ∈ S}``."""
        raise BalustradeError(f"{self.name}.translate: not available for {type(self).__name__}")

    def minkowski_sum(self, other: Set, name: str | None = None) -> Set:
        """``S ⊕ T`` (SPEC §1.5); exact or an outer approximation, see the module table."""
        from balustrade.dsl import sets_ops

        return sets_ops.minkowski_sum(self, other, name)

    def pontryagin_difference(self, other: Set, name: str | None = None) -> Set:
        """``S ⊖ T = {x : x + t ∈ S ∀ t ∈ T}`` (SPEC §1.5)."""
        raise BalustradeError(f"{self.name} ⊖ {getattr(other, 'name', other)}: the Pontryagin "
                              f"difference has no closed form for a {type(self).__name__}; "
                              "use a Polytope or Box as the minuend")

    def is_subset_of(self, other: Set, tol: float = 1e-7) -> bool:
        """Whether ``S ⊆ T``, up to ``tol`` in the units of ``T.c`` (see module table)."""
        from balustrade.dsl import sets_ops

        self._check_same_dim(other, "⊆")
        return sets_ops.is_subset(self, other, check_tol(tol, f"{self.name} ⊆ {other.name}"))

    def sample(self, n: int, rng: RngLike = None) -> np.ndarray:
        """``n`` points drawn uniformly from the set, shape ``(n, dim)``."""
        raise BalustradeError(f"{self.name}.sample: not available for {type(self).__name__}")

    def project(self, x: np.ndarray) -> np.ndarray:
        """The Euclidean projection ``argmin_{y ∈ S} ‖y − x‖₂`` of the finite point ``x``
        (exact: clipping for a box, algorithm LDP for a polytope, a root search on the
        multiplier for an ellipsoid; :mod:`balustrade.dsl.sets_project`)."""
        return self._project(as_vector(x, f"{self.name}.project(x)", self.dim))

    def _project(self, x: np.ndarray) -> np.ndarray:
        raise BalustradeError(f"{self.name}.project: no exact projection onto a "
                              f"{type(self).__name__} (use a Box, Polytope or Ellipsoid)")


def linear_map(A: np.ndarray, S: Set, name: str | None = None) -> Set:
    """``A·S`` (SPEC §1.5); same as ``S.linear_map(A)`` and ``A @ S``."""
    return S.linear_map(A, name=name)


def minkowski_sum(A: Set, B: Set, name: str | None = None) -> Set:
    """``A ⊕ B`` (SPEC §1.5); same as ``A.minkowski_sum(B)``."""
    return A.minkowski_sum(B, name=name)


def pontryagin_difference(A: Set, B: Set, name: str | None = None) -> Set:
    """``A ⊖ B`` (SPEC §1.5); same as ``A.pontryagin_difference(B)``."""
    return A.pontryagin_difference(B, name=name)

