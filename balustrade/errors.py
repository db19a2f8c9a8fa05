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


class UnprovenCheckWarning(BalustradeWarning):
    """A check that could only search for counterexamples (sampled directions and points)
    found none: its ``ok`` is not a proof (e.g. :func:`~balustrade.dsl.error_sets.is_rpi`
    for an ellipsoid when ``A + BK`` is singular or ``W`` is not a polytope); the result
    records it (``proven=False``)."""


class TighteningWarning(BalustradeWarning):
    """Tightenings ``Δ_i`` that are increasing but not strictly (e.g. all zero): the PCBF
    problems are well posed, but the strict decrease of the slack cost (SPEC §1.4) is lost."""


def moved_names(module: str, moved: dict[str, str]):
    """A module ``__getattr__`` (PEP 562) for names that moved in the restructuring of issue
    #13 (solvers and algorithms out of ``problems/``, examples out of ``models/``/``learn/``):
    ``moved`` maps each name to its new module. Importing one from the old module still works
    for scripts written against the old layout, with a :class:`DeprecationWarning` naming the
    new home. The new module is imported only when such a name is asked for, so the module
    itself keeps its layer's imports (``tests/test_import_rules.py``)."""

    def __getattr__(name: str) -> object:
        if name not in moved:
            raise AttributeError(f"module {module!r} has no attribute {name!r}")
        import importlib
        import warnings

        warnings.warn(f"{module}.{name} moved to {moved[name]}.{name} (issue #13); import it "
                      f"from {moved[name]}", DeprecationWarning, stacklevel=2)
        return getattr(importlib.import_module(moved[name]), name)

    __getattr__.moved = dict(moved)  # type: ignore[attr-defined]  # for tests and tools
    return __getattr__
