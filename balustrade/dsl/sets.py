"""Sets used as constraints, disturbance bounds, error sets and terminal sets.

Every set is written as ``{x : c(x) <= 0}`` (SPEC §1.3) so that the horizon problem builder
can impose ``x ∈ S`` (hard), ``c(x) <= ξ`` (soft, slack ξ) or ``c(x) + Δ_i <= ξ``
(tightened, SPEC §1.4) for any set, whatever its kind:

* :class:`Polytope` ``{x : H x <= h}`` with ``c(x) = H x - h`` (rows not normalised, SPEC §1.3),
* :class:`Box` ``{lb <= x <= ub}`` (a polytope with ``H = [I; -I]``),
* :class:`Ellipsoid` ``{x : (x - q)ᵀ P (x - q) <= 1}`` with ``c(x) = (x - q)ᵀ P (x - q) - 1``,
* :class:`FunctionSet` ``{x : c(x) <= 0}`` for any CasADi-callable ``c``.

Tightening uses support functions only (SPEC §1.5): ``{Hx <= h} ⊖ B = {Hx <= h - [h_B(H_jᵀ)]_j}``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import casadi as ca
import numpy as np
import scipy.optimize

from balustrade._checks import as_matrix, as_vector, check_psd
from balustrade.errors import BalustradeError, EmptySetError, ShapeError

Symbolic = ca.SX | ca.MX | ca.DM


class Set:
    """A closed set ``{x ∈ R^dim : c(x) <= 0}``."""

    dim: int
    name: str

    def c(self, x: Symbolic) -> Symbolic:
        """Constraint function rows ``c(x)`` (a column), ``x ∈ S ⟺ c(x) <= 0``."""
        raise NotImplementedError  # pragma: no cover - abstract

    @property
    def n_rows(self) -> int:
        """Number of rows of ``c``."""
        return int(self.c(ca.SX.sym("x", self.dim)).numel())

    def support(self, a: np.ndarray) -> float:
        """Support function ``h_S(a) = max_{x∈S} aᵀx``."""
        raise NotImplementedError  # pragma: no cover - abstract

    def contains(self, x: np.ndarray, tol: float = 1e-9) -> bool:
        """Whether the point ``x`` lies in the set (up to ``tol``)."""
        x = as_vector(x, f"{self.name}.contains(x)", self.dim)
        return bool(np.all(np.asarray(ca.evalf(self.c(ca.DM(x)))).ravel() <= tol))

    def _check_point_dim(self, x: Symbolic, block: str) -> None:
        if x.shape != (self.dim, 1):
            raise ShapeError(f"{block} of {self.name}", (self.dim, 1), x.shape)


@dataclass(frozen=True, eq=False)
class Polytope(Set):
    """H-polytope ``{x : H x <= h}`` (SPEC §1.3, polytopic form)."""

    H: np.ndarray
    h: np.ndarray
    name: str = "Polytope"

    def __post_init__(self) -> None:
        H = as_matrix(self.H, f"{self.name}: H")
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

    def is_empty(self) -> bool:
        """Whether ``{Hx <= h}`` is empty (one LP)."""
        res = scipy.optimize.linprog(np.zeros(self.dim), A_ub=self.H, b_ub=self.h,
                                     bounds=[(None, None)] * self.dim, method="highs")
        return res.status == 2

    def support(self, a: np.ndarray) -> float:
        a = as_vector(a, f"{self.name}.support(a)", self.dim)
        res = scipy.optimize.linprog(-a, A_ub=self.H, b_ub=self.h,
                                     bounds=[(None, None)] * self.dim, method="highs")
        if res.status == 3:
            return float("inf")
        if res.status != 0:
            raise BalustradeError(f"{self.name}.support: LP failed ({res.message})")
        return float(-res.fun)

    def tighten(self, other: Set, name: str | None = None) -> Polytope:
        """Pontryagin difference ``self ⊖ other`` by support functions (SPEC §1.5)."""
        if other.dim != self.dim:
            raise ShapeError(f"{self.name} ⊖ {other.name}", f"a set of dimension {self.dim}",
                             f"dimension {other.dim}")
        s = np.array([other.support(row) for row in self.H])
        h_new = self.h - s
        new_name = name or f"{self.name}⊖{other.name}"
        try:
            return Polytope(self.H, h_new, name=new_name)
        except EmptySetError as exc:
            raise EmptySetError(f"tightening {self.name} by {other.name} leaves an empty set "
                                f"({new_name})") from exc


class Box(Polytope):
    """Axis-aligned box ``{lb <= x <= ub}``; ``c(x) = [x - ub; lb - x]``."""

    def __init__(self, lb: np.ndarray, ub: np.ndarray, name: str = "Box"):
        lb = as_vector(lb, f"{name}: lb", finite=False)
        ub = as_vector(ub, f"{name}: ub", lb.size, finite=False)
        if np.any(np.isnan(lb)) or np.any(np.isnan(ub)):
            raise BalustradeError(f"{name}: bounds contain NaN")
        if np.any(lb > ub):
            raise EmptySetError(f"{name}: lower bound exceeds upper bound at "
                                f"indices {np.flatnonzero(lb > ub).tolist()}")
        keep_u = np.isfinite(ub)
        keep_l = np.isfinite(lb)
        n = lb.size
        H = np.vstack([np.eye(n)[keep_u], -np.eye(n)[keep_l]])
        h = np.concatenate([ub[keep_u], -lb[keep_l]])
        object.__setattr__(self, "lb", lb)
        object.__setattr__(self, "ub", ub)
        object.__setattr__(self, "_n", n)
        super().__init__(H.reshape(-1, n), h, name=name)

    @classmethod
    def symmetric(cls, bound: np.ndarray | float, dim: int | None = None,
                  name: str = "Box") -> Box:
        """``{|x_i| <= bound_i}``."""
        b = np.atleast_1d(np.asarray(bound, dtype=float))
        if dim is not None and b.size == 1:
            b = np.full(dim, float(b[0]))
        return cls(-b, b, name=name)

    @property
    def dim(self) -> int:  # type: ignore[override]
        return int(self._n)

    def support(self, a: np.ndarray) -> float:
        a = as_vector(a, f"{self.name}.support(a)", self.dim)
        vals = np.where(a > 0, a * self.ub, np.where(a < 0, a * self.lb, 0.0))
        return float(np.sum(vals))

    def vertices(self) -> np.ndarray:
        """All ``2^dim`` vertices (rows)."""
        if not (np.all(np.isfinite(self.lb)) and np.all(np.isfinite(self.ub))):
            raise BalustradeError(f"{self.name}: unbounded box has no vertices")
        grids = np.meshgrid(*[[lo, hi] for lo, hi in zip(self.lb, self.ub)], indexing="ij")
        return np.stack([g.ravel() for g in grids], axis=1)


@dataclass(frozen=True, eq=False)
class Ellipsoid(Set):
    """``{x : (x - center)ᵀ P (x - center) <= 1}`` with ``P ≻ 0``."""

    P: np.ndarray
    center: np.ndarray | None = None
    name: str = "Ellipsoid"

    def __post_init__(self) -> None:
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

    def c(self, x: Symbolic) -> Symbolic:
        self._check_point_dim(x, "c(x)")
        d = x - ca.DM(self.center)
        return ca.mtimes([d.T, ca.DM(self.P), d]) - 1

    def support(self, a: np.ndarray) -> float:
        """``h(a) = aᵀq + sqrt(aᵀ P⁻¹ a)`` (SPEC §1.4)."""
        a = as_vector(a, f"{self.name}.support(a)", self.dim)
        return float(a @ self.center + np.sqrt(max(a @ np.linalg.solve(self.P, a), 0.0)))


class FunctionSet(Set):
    """``{x : c(x) <= 0}`` for a CasADi-callable ``c`` (SPEC (2.8)).

    ``c`` takes a ``(dim, 1)`` CasADi symbol and returns a column of constraint rows. The
    convex backend accepts it only where it detects affine or convex-quadratic rows;
    anything else is refused there with an error naming this set.
    """

    def __init__(self, c: Callable[[Symbolic], Symbolic], dim: int, name: str = "FunctionSet"):
        self._fun = c
        self.dim = int(dim)
        self.name = name
        try:
            out = c(ca.SX.sym("x", self.dim))
        except Exception as exc:  # the user's function failed on a symbol
            raise BalustradeError(f"{name}: c(x) failed on a CasADi symbol of shape "
                                  f"({self.dim}, 1): {exc}") from exc
        out = ca.SX(out) if not isinstance(out, ca.SX) else out
        if out.shape[1] != 1 and out.shape[0] != 1:
            raise ShapeError(f"{name}: c(x)", "a column of constraint rows", out.shape)

    def c(self, x: Symbolic) -> Symbolic:
        self._check_point_dim(x, "c(x)")
        out = self._fun(x)
        return ca.vec(out)

    def support(self, a: np.ndarray) -> float:
        """Support value by a local NLP (exact when ``c`` is convex)."""
        a = as_vector(a, f"{self.name}.support(a)", self.dim)
        x = ca.SX.sym("x", self.dim)
        solver = ca.nlpsol("support", "ipopt", {"x": x, "f": -ca.dot(ca.DM(a), x),
                                                "g": self.c(x)},
                           {"ipopt.print_level": 0, "print_time": False,
                            "ipopt.sb": "yes"})
        res = solver(x0=np.zeros(self.dim), ubg=0)
        if not solver.stats()["success"]:
            raise BalustradeError(f"{self.name}.support: NLP failed "
                                  f"({solver.stats()['return_status']})")
        return float(-res["f"])
