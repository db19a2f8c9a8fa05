"""Backends: lower an :class:`~balustrade.dsl.ocp.OCP` to a solver, once.

``compile(ocp, backend="casadi" | "cvxpy", solver=..., options=...)`` returns an object
with ``solve(params, warm_start=None) -> Solution``.
"""

from __future__ import annotations

from balustrade.backends.casadi_backend import CasadiCompiled
from balustrade.backends.cvxpy_backend import CvxpyCompiled
from balustrade.backends.solution import Solution
from balustrade.dsl.ocp import OCP
from balustrade.errors import BalustradeError, SolverError

Compiled = CasadiCompiled | CvxpyCompiled

BACKENDS = {"casadi": CasadiCompiled, "cvxpy": CvxpyCompiled}


def compile(ocp: OCP, backend: str = "casadi", solver: str | None = None,
            options: dict | None = None,
            retries: list[tuple[str, dict]] | None = None) -> Compiled:
    """Compile ``ocp`` for ``backend``; CasADi's default solver is IPOPT, cvxpy's is PIQP
    for LPs/QPs and Clarabel for conic problems. ``retries`` (CasADi only) replaces the
    default retry chain after a failed solve (``[]`` turns retries off, e.g. for closed
    loops that have their own fallbacks)."""
    if not isinstance(ocp, OCP):
        raise BalustradeError(f"compile: expected a balustrade OCP, got {type(ocp).__name__}")
    if not isinstance(backend, str) or backend not in BACKENDS:
        raise SolverError(f"{ocp.name}: unknown backend {backend!r}; use one of "
                          f"{', '.join(BACKENDS)}")
    if backend == "casadi":
        return CasadiCompiled(ocp, solver or "ipopt", options, retries)
    return CvxpyCompiled(ocp, solver, options)


__all__ = ["BACKENDS", "CasadiCompiled", "Compiled", "CvxpyCompiled", "Solution", "compile"]
