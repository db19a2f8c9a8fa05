"""balustrade: a modeling language for safe predictive control.

State a formulation (dynamics, soft constraints, tightenings, tubes, terminal CBFs,
decrease constraints, costs) with :class:`balustrade.dsl.OCP`, compile it to CasADi or
cvxpy with :func:`balustrade.compile`, verify solutions with :func:`balustrade.verify`,
and run it in closed loop with :mod:`balustrade.control`.
"""

from balustrade.errors import (
    BalustradeError,
    CodegenError,
    ConvexityError,
    EmptySetError,
    NonFiniteError,
    NotPSDError,
    ShapeError,
    SolverError,
)

__version__ = "0.1.0"


def __getattr__(name: str) -> object:
    """``balustrade.compile``, ``balustrade.verify`` and ``balustrade.Status``, imported on
    first use (they pull in CasADi and cvxpy; ``import balustrade`` stays light)."""
    if name == "compile":
        from balustrade.backends import compile

        return compile
    if name == "Status":
        from balustrade.backends.solution import Status

        return Status
    if name == "verify":
        from balustrade.testing import verify

        return verify
    raise AttributeError(f"module 'balustrade' has no attribute {name!r}")


__all__ = [
    "BalustradeError",
    "CodegenError",
    "ConvexityError",
    "EmptySetError",
    "NonFiniteError",
    "NotPSDError",
    "ShapeError",
    "SolverError",
    "Status",
    "__version__",
    "compile",
    "verify",
]
