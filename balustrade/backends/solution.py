"""The one result type every backend returns."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

SUCCESS_STATUSES = ("optimal", "optimal_inaccurate")


@dataclass
class Solution:
    """Result of one solve.

    ``status`` is one of ``optimal``, ``optimal_inaccurate``, ``feasible`` (no convergence,
    but a primal-feasible point), ``infeasible``, ``max_iterations``, ``failed``; ``primal``
    maps variable names to arrays of their declared shapes; ``dual`` maps constraint-block
    names (and ``bound:<variable>``) to multipliers; ``objective`` is the declared cost
    evaluated at the primal solution.
    ``w`` is the stacked decision vector (declaration order), ``p`` the stacked parameters.
    """

    status: str
    objective: float
    primal: dict[str, np.ndarray]
    dual: dict[str, np.ndarray]
    solve_time: float
    iterations: int
    backend: str
    solver: str
    w: np.ndarray
    p: np.ndarray
    message: str = ""
    raw: dict = field(default_factory=dict, repr=False)

    @property
    def success(self) -> bool:
        return self.status in SUCCESS_STATUSES

    @property
    def usable(self) -> bool:
        """Converged, or at least primal feasible: safe to apply in a closed loop."""
        return self.success or self.status == "feasible"

    def __getitem__(self, name: str) -> np.ndarray:
        return self.primal[name]

    def summary(self) -> str:
        return (f"{self.backend}/{self.solver}: {self.status}, objective {self.objective:.6g}, "
                f"{self.iterations} iterations, {self.solve_time * 1e3:.2f} ms"
                + (f" ({self.message})" if self.message else ""))
