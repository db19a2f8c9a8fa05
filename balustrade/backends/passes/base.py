"""What a lowering pass is: a small object with ``accepts``/``apply``/``invert``.

Modelled on cvxpy's reductions (DESIGN.md, "Models to learn from"): ``apply`` rewrites a
problem into a simpler one and returns the data its ``invert`` needs to map a solution of the
simpler problem back to the problem it was given. A backend is a chain of passes whose last
one produces what the solver takes (:mod:`balustrade.backends.passes`).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import Any

from balustrade.errors import BalustradeError


class Pass(ABC):
    """One lowering step. Subclasses set :attr:`name` and implement :meth:`apply`."""

    name = "pass"

    def accepts(self, problem: Any) -> bool:
        """Whether :meth:`apply` can take ``problem`` (the chain refuses it otherwise)."""
        return True

    @abstractmethod
    def apply(self, problem: Any) -> tuple[Any, Any]:
        """``(lowered problem, inverse data)``."""

    def invert(self, solution: Any, inverse: Any) -> Any:
        """Map a solution of the lowered problem back (the identity by default)."""
        return solution


def run_chain(chain: Sequence[Pass], problem: Any) -> tuple[Any, list[tuple[Pass, Any]]]:
    """Apply ``chain`` in order: the last problem and, per pass, its inverse data (in the
    order :func:`invert_chain` undoes them)."""
    inverses = []
    for step in chain:
        if not step.accepts(problem):
            raise BalustradeError(f"lowering pass {step.name!r} cannot take "
                                  f"{type(problem).__name__}")
        problem, inverse = step.apply(problem)
        inverses.append((step, inverse))
    return problem, inverses


def invert_chain(inverses: Sequence[tuple[Pass, Any]], solution: Any) -> Any:
    """Map a solution of the last problem back through the passes, last pass first."""
    for step, inverse in reversed(inverses):
        solution = step.invert(solution, inverse)
    return solution
