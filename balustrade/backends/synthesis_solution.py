"""The one result type of a synthesis problem (SDP/SOCP) solve."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from balustrade.backends.targets import Target
from balustrade.errors import BalustradeError

#: statuses a synthesis solve can end with: those of :class:`~balustrade.backends.Solution`
#: plus ``unbounded`` (an SDP whose objective has no bound is a modelling error worth naming)
SYNTHESIS_STATUSES = ("optimal", "optimal_inaccurate", "infeasible", "unbounded",
                      "max_iterations", "failed")
SUCCESS_STATUSES = ("optimal", "optimal_inaccurate")


@dataclass
class SynthesisSolution:
    """Result of one :meth:`CompiledSynthesis.solve`.

    ``status`` is one of :data:`SYNTHESIS_STATUSES`; ``message`` says why in words (cvxpy's
    status, the solver's own status, an exception text, or a refusal such as a PSD cone too
    large for the memory). ``values`` maps variable names to arrays of their declared
    shapes (empty unless :attr:`ok`), ``duals`` maps constraint names to multipliers (a list
    of arrays for a second-order cone: those of ``t`` and of ``x``), ``objective`` is the
    optimal value, ``solve_time`` the wall time of the solve (s), ``solver_time`` the
    solver's own time when it reports one, ``target`` the target used.
    """

    status: str
    message: str = ""
    values: dict[str, np.ndarray] = field(default_factory=dict)
    duals: dict[str, np.ndarray | list[np.ndarray]] = field(default_factory=dict)
    objective: float = float("nan")
    solve_time: float = 0.0
    solver_time: float = float("nan")
    target: Target | None = None
    info: dict = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        if self.status not in SYNTHESIS_STATUSES:
            raise BalustradeError(f"SynthesisSolution: unknown status {self.status!r}; one of "
                                  f"{', '.join(SYNTHESIS_STATUSES)}")

    @property
    def ok(self) -> bool:
        """Whether the solve succeeded (``optimal`` or ``optimal_inaccurate``)."""
        return self.status in SUCCESS_STATUSES

    def __getitem__(self, name: str) -> np.ndarray:
        """The value of variable ``name`` (raises naming the status when there is none)."""
        if name not in self.values:
            why = (f"the solve ended {self.status!r}: {self.message}" if not self.ok
                   else f"variables: {', '.join(self.values)}")
            raise BalustradeError(f"SynthesisSolution: no value for {name!r} ({why})")
        return self.values[name]


__all__ = ["SUCCESS_STATUSES", "SYNTHESIS_STATUSES", "SynthesisSolution"]
