"""Exceptions raised by balustrade.

Every error names the block (a constraint, a set, a system, a parameter) it concerns and,
for shape problems, the expected and the given shape, before any solver runs.
"""

from __future__ import annotations


class BalustradeError(Exception):
    """Base class of all balustrade errors."""


class ShapeError(BalustradeError, ValueError):
    """An array or expression has the wrong shape for the block it is given to."""

    def __init__(self, block: str, expected: object, given: object,
                 what: str | None = None):
        self.block, self.expected, self.given = block, expected, given
        got = f"shape {given}" if isinstance(given, tuple) else str(given)
        if what is not None:  # the caller words it: "expected <what> <expected>"
            exp = f"{what} {expected}".strip()
        else:
            exp = f"shape {expected}" if isinstance(expected, tuple) else str(expected)
        super().__init__(f"{block}: expected {exp}, got {got}")


class NonFiniteError(BalustradeError, ValueError):
    """A numeric input contains NaN or inf."""


class NotPSDError(BalustradeError, ValueError):
    """A matrix that must be positive (semi)definite is not."""


class EmptySetError(BalustradeError, ValueError):
    """A set is empty (e.g. an infeasible polytope, or a tightening that removed everything)."""


class ConvexityError(BalustradeError, ValueError):
    """A block cannot be represented by a convex (cvxpy) backend."""


class SolverError(BalustradeError, ValueError):
    """Unknown solver name, or a solver that cannot do what was asked."""


class CodegenError(BalustradeError, RuntimeError):
    """C code generation, compilation or loading failed."""


class BalustradeWarning(UserWarning):
    """Base class of balustrade warnings: a result is returned, but read it with care."""


class DegenerateResultWarning(BalustradeWarning):
    """A synthesis succeeded but its result is degenerate (e.g. a terminal CBF level
    ``γ_f ≈ 0``); the result names the reason."""


class MovedError(BalustradeError, ImportError):
    """A name that moved to another module in the restructuring of issue #13 (solvers and
    algorithms out of ``problems/``): the message names the new home."""


def moved_names(module: str, moved: dict[str, str]):
    """A module ``__getattr__`` (PEP 562) that refuses the names in ``moved`` (name → new
    module) with a :class:`MovedError` saying where each one lives now, instead of Python's
    bare "cannot import name". It imports nothing, so the layering is kept."""

    def __getattr__(name: str) -> object:
        if name in moved:
            raise MovedError(f"{module}.{name} moved to {moved[name]}.{name} (issue #13: "
                             f"{module.split('.')[1]}/ no longer holds it); import it from "
                             f"{moved[name]}")
        raise AttributeError(f"module {module!r} has no attribute {name!r}")

    __getattr__.moved = dict(moved)  # type: ignore[attr-defined]  # for tests and tools
    return __getattr__
