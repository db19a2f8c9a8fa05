"""User-defined sets ``{x : c(x) <= 0}`` for a CasADi-callable ``c`` (SPEC (2.8)).

The support function of such a set needs an NLP solver, and the language names none (it
imports no backend, issue #13 §1). So :meth:`FunctionSet.support` calls a *support solver*:
the one given to the set (``FunctionSet(..., support=fn)``), else the default registered with
:func:`register_support_solver` — :mod:`balustrade.backends` registers its local NLP
(:func:`balustrade.backends.set_support.function_set_support`) when it is imported. Without
either, ``support`` (and what uses it: ``bounding_box``, ``is_subset_of`` into a polytope)
raises an error saying so.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import casadi as ca
import numpy as np

from balustrade._checks import as_count, as_vector, check_callable, check_name, check_symbolic
from balustrade.dsl.sets_base import RngLike, Set, Symbolic, as_rng, check_count, check_scalar
from balustrade.errors import BalustradeError, ShapeError

if TYPE_CHECKING:
    from balustrade.dsl.sets import Box

#: ``support(fset, a) -> float``: ``max {aᵀx : fset.c(x) <= 0}`` (``a`` checked, 1-D)
SupportSolver = Callable[["FunctionSet", np.ndarray], float]

_DEFAULT_SUPPORT: list[SupportSolver] = []


def register_support_solver(fn: SupportSolver) -> None:
    """Make ``fn`` the default support solver of every :class:`FunctionSet` without its own
    (:mod:`balustrade.backends` registers its NLP on import)."""
    check_callable(fn, "register_support_solver: fn")
    _DEFAULT_SUPPORT[:] = [fn]


class FunctionSet(Set):
    """``{x : c(x) <= 0}`` for a CasADi-callable ``c`` (SPEC (2.8)).

    ``c`` takes a ``(dim, 1)`` CasADi symbol and returns a column of constraint rows. The
    convex backend accepts it only where it detects affine or convex-quadratic rows;
    anything else is refused there with an error naming this set.

    ``support`` (optional): the support solver of this set, ``support(set, a) -> float``
    (module docstring); ``None`` uses the registered default.
    """

    def __init__(self, c: Callable[[Symbolic], Symbolic], dim: int, name: str = "FunctionSet",
                 support: SupportSolver | None = None):
        self.name = check_name(name, "FunctionSet: name")
        check_callable(c, f"{name}: c")
        if support is not None:
            check_callable(support, f"{name}: support")
        self._fun, self._support = c, support
        self.dim = as_count(dim, f"{name}: dim", low=1)
        try:
            out = c(ca.SX.sym("x", self.dim))
        except Exception as exc:  # the user's function failed on a symbol
            raise BalustradeError(f"{name}: c(x) failed on a CasADi symbol of shape "
                                  f"({self.dim}, 1): {exc}") from exc
        try:
            out = ca.SX(out) if not isinstance(out, ca.SX) else out
        except Exception as exc:  # noqa: BLE001 - not a CasADi expression
            raise BalustradeError(f"{name}: c(x) returned a {type(out).__name__}, not a "
                                  f"CasADi expression ({exc})") from exc
        if out.shape[1] != 1 and out.shape[0] != 1:
            raise ShapeError(f"{name}: c(x)", "a column of constraint rows", out.shape)
        if out.numel() == 0:
            raise ShapeError(f"{name}: c(x)", "at least one constraint row", out.shape)
        check_symbolic(out, f"{name}: c(x)")

    def __repr__(self) -> str:
        return f"FunctionSet(dim={self.dim}, name={self.name!r})"

    def c(self, x: Symbolic) -> Symbolic:
        self._check_point_dim(x, "c(x)")
        out = self._fun(x)
        return ca.vec(out)

    def support(self, a: np.ndarray) -> float:
        """Support value ``max {aᵀx : c(x) <= 0}`` by the set's support solver (module
        docstring; the backends' local NLP is exact when ``c`` is convex and refuses a row
        that is not provably convex: affine or a convex quadratic)."""
        a = as_vector(a, f"{self.name}.support(a)", self.dim)
        fn = self._support or (_DEFAULT_SUPPORT[0] if _DEFAULT_SUPPORT else None)
        if fn is None:
            raise BalustradeError(f"{self.name}.support: no support solver; import "
                                  "balustrade.backends (it registers its NLP) or give "
                                  "FunctionSet(..., support=fn)")
        return float(fn(self, a))

    def linear_map(self, A: np.ndarray, name: str | None = None) -> FunctionSet:
        """``A·S = {y : c(A⁻¹y) <= 0}`` for invertible square ``A``."""
        A = self._map_matrix(A)
        if A.shape[0] != A.shape[1] or np.linalg.matrix_rank(A) < self.dim:
            raise BalustradeError(f"{self.name}.linear_map: a FunctionSet of dimension "
                                  f"{self.dim} can only be mapped by an invertible square "
                                  f"matrix, got A of shape {A.shape}")
        Ainv = ca.DM(np.linalg.inv(A))
        return FunctionSet(lambda y: self.c(ca.mtimes(Ainv, y)), self.dim,
                           name=name or f"A·{self.name}", support=self._support)

    def scale(self, alpha: float, name: str | None = None) -> FunctionSet:
        a = check_scalar(alpha, f"{self.name}.scale")
        if a == 0.0:
            raise BalustradeError(f"{self.name}.scale: 0·{self.name} is a point")
        return FunctionSet(lambda y: self.c(y / a), self.dim, name=name or f"{a:g}·{self.name}",
                           support=self._support)

    def translate(self, v: np.ndarray, name: str | None = None) -> FunctionSet:
        v = ca.DM(as_vector(v, f"{self.name}.translate(v)", self.dim))
        return FunctionSet(lambda y: self.c(y - v), self.dim, name=name or f"{self.name}+v",
                           support=self._support)

    def sample(self, n: int, rng: RngLike = None, bounds: Box | None = None,
               max_draws: int = 1_000_000) -> np.ndarray:
        """Uniform samples by rejection from the user-given bounded ``bounds`` box, which must
        contain the set (points outside it are never drawn)."""
        from balustrade.dsl.sets import Box

        n = check_count(n, f"{self.name}.sample")
        if not isinstance(bounds, Box):
            raise BalustradeError(f"{self.name}.sample: a FunctionSet needs bounds=Box(lb, ub) "
                                  "enclosing it to sample by rejection")
        if bounds.dim != self.dim:
            raise ShapeError(f"{self.name}.sample(bounds)", f"a Box of dimension {self.dim}",
                             f"dimension {bounds.dim}")
        g = as_rng(rng)
        chunks, got, draws = [], 0, 0
        while got < n and draws < max_draws:
            X = bounds.sample(max(1000, 2 * (n - got)), g)
            draws += X.shape[0]
            ok = self.contains_many(X, tol=0.0)
            chunks.append(X[ok])
            got += int(ok.sum())
        if got < n:
            raise BalustradeError(f"{self.name}.sample: only {got} of {draws} draws from "
                                  f"{bounds.name} fell in the set; give tighter bounds")
        return np.concatenate(chunks)[:n] if chunks else np.empty((0, self.dim))


