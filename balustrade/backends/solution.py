"""The one result type every backend returns."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from balustrade._checks import as_float_array
from balustrade.errors import BalustradeError, ShapeError


class Status(StrEnum):
    """The outcome of one solve, the same for every backend (a ``str`` enum:
    ``status == "optimal"``, f-strings and JSON see the plain value)."""

    OPTIMAL = "optimal"
    OPTIMAL_INACCURATE = "optimal_inaccurate"
    #: no convergence, but a primal-feasible point (CasADi's rescue of a failed solve)
    FEASIBLE = "feasible"
    INFEASIBLE = "infeasible"
    #: kept for solvers that certify it; the backends report an apparently unbounded
    #: problem as ``FAILED`` with a message saying so (a well-posed filter is never unbounded)
    UNBOUNDED = "unbounded"
    MAX_ITERATIONS = "max_iterations"
    FAILED = "failed"

    @property
    def success(self) -> bool:
        return self in SUCCESS_STATUSES

    @classmethod
    def of(cls, value: object) -> Status:
        """``Status(value)`` or an error listing the statuses."""
        try:
            return cls(value)
        except ValueError:
            raise BalustradeError(f"Solution: unknown status {value!r}; use one of "
                                  f"{[s.value for s in cls]}") from None


SUCCESS_STATUSES = (Status.OPTIMAL, Status.OPTIMAL_INACCURATE)

#: the largest violation (absolute) of a constraint row or variable bound at which a
#: truncated solve's iterate counts as feasible (:meth:`Solution.feasible_within`); the
#: CasADi backend's rescue of a failed solve uses the same 1e-8
FEASIBILITY_TOL = 1e-8


@dataclass(init=False)
class Solution:
    """Result of one solve.

    ``status`` is a :class:`Status` (a string given for it is converted, an unknown one
    refused): ``optimal``, ``optimal_inaccurate``, ``feasible`` (no convergence, but a
    primal-feasible point), ``infeasible``, ``max_iterations``, ``failed``; ``primal``
    maps variable names to arrays of their declared shapes; ``dual`` maps constraint-block
    names (and ``bound:<variable>``) to multipliers; ``objective`` is the declared cost
    evaluated at the primal solution; ``p`` is the stacked parameter vector.

    ``truncated`` (real-time mode, issue #14 §5): the solve was stopped by the target's
    budget (:meth:`~balustrade.backends.targets.Target.with_budget`) before converging; its
    status is then ``max_iterations`` (never ``optimal``) and ``primal_residual`` is the
    largest violation of a constraint row or variable bound at the returned iterate (``nan``
    when not computed), so :meth:`feasible_within` tells "stopped early at a feasible point"
    from "stopped infeasible".

    ``primal`` is the one source of truth for the point: ``w``, the stacked decision vector
    (declaration order, column-major per variable), is derived from it on every access, so
    editing ``sol.primal["u"]`` (in place or by assignment) changes ``sol.w`` and what
    :func:`balustrade.verify` checks. Assigning ``sol.w`` writes back into ``primal``, and so
    does a ``w`` given to the constructor (``Solution(**{**sol.__dict__, "w": w2})`` is the
    point ``w2``); the constructor copies the ``primal`` dict, so solutions never share it.
    """

    status: Status
    objective: float
    primal: dict[str, np.ndarray]
    dual: dict[str, np.ndarray]
    solve_time: float
    iterations: int
    backend: str
    solver: str
    p: np.ndarray
    message: str = ""
    raw: dict = field(default_factory=dict, repr=False)
    truncated: bool = False
    primal_residual: float = float("nan")

    def __init__(self, status: Status | str, objective: float, primal: dict[str, np.ndarray],
                 dual: dict[str, np.ndarray], solve_time: float, iterations: int,
                 backend: str, solver: str, w: np.ndarray | None = None,
                 p: np.ndarray | None = None, message: str = "",
                 raw: dict | None = None, truncated: bool = False,
                 primal_residual: float = float("nan")):
        if not isinstance(primal, dict):
            raise BalustradeError(f"Solution: primal must be a dict name -> array, got "
                                  f"{type(primal).__name__}")
        primal = dict(primal)
        self.status, self.objective, self.primal, self.dual = status, objective, primal, dual
        self.solve_time, self.iterations = solve_time, iterations
        self.backend, self.solver, self.message = backend, solver, message
        self.p = np.zeros(0) if p is None else as_float_array(p, "Solution: p").reshape(-1)
        self.raw = {} if raw is None else raw
        self.truncated, self.primal_residual = bool(truncated), float(primal_residual)
        if w is not None:
            given = as_float_array(w, "Solution: w").reshape(-1)
            if not np.array_equal(given, self.w, equal_nan=True):
                self.w = given  # checks the size against primal's, then writes primal

    def __setattr__(self, name: str, value: object) -> None:
        if name == "status":  # a str from the caller becomes the enum (or an error)
            value = value if type(value) is Status else Status.of(value)
        # a truncated solve is never optimal, whichever of the two is set last
        status = value if name == "status" else getattr(self, "status", None)
        if (value if name == "truncated" else getattr(self, "truncated", False)) \
                and name in ("status", "truncated") and status in SUCCESS_STATUSES:
            raise BalustradeError(f"Solution: a truncated solve cannot be {status!r} "
                                  f"(it stopped before converging)")
        object.__setattr__(self, name, value)

    @property
    def w(self) -> np.ndarray:
        """The stacked decision vector, derived from :attr:`primal` (declaration order)."""
        chunks = [as_float_array(v, f"Solution.primal[{k!r}]").reshape(-1, order="F")
                  for k, v in self.primal.items()]
        return np.concatenate(chunks) if chunks else np.zeros(0)

    @w.setter
    def w(self, value: np.ndarray) -> None:
        value = as_float_array(value, "Solution.w").reshape(-1)
        sizes = [np.size(v) for v in self.primal.values()]
        if value.size != sum(sizes):
            raise ShapeError("Solution.w", (sum(sizes),), value.shape)
        k = 0
        for (name, old), n in zip(list(self.primal.items()), sizes):
            self.primal[name] = value[k:k + n].reshape(np.shape(old), order="F").copy()
            k += n

    @property
    def success(self) -> bool:
        return self.status in SUCCESS_STATUSES

    @property
    def usable(self) -> bool:
        """Converged, or at least primal feasible: safe to apply in a closed loop."""
        return self.success or self.status == Status.FEASIBLE

    def feasible_within(self, tol: float = FEASIBILITY_TOL) -> bool:
        """The returned point meets every constraint row and bound up to ``tol`` (absolute),
        as measured by :attr:`primal_residual` (``False`` when it was not computed)."""
        return bool(self.primal_residual <= tol)

    def __getitem__(self, name: str) -> np.ndarray:
        try:
            return self.primal[name]
        except (KeyError, TypeError):
            raise BalustradeError(f"Solution: no variable named {name!r}; the solution has "
                                  f"{list(self.primal)}") from None

    def summary(self) -> str:
        status = f"{self.status} (truncated)" if self.truncated else str(self.status)
        return (f"{self.backend}/{self.solver}: {status}, objective {self.objective:.6g}, "
                f"{self.iterations} iterations, {self.solve_time * 1e3:.2f} ms"
                + (f" ({self.message})" if self.message else ""))
