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
    if ocp.decision_vector().numel() == 0:
        raise BalustradeError(f"compile: {ocp.name} has no decision variables (declare them "
                              "with OCP(system, N) or ocp.variable)")
    if solver is not None and not isinstance(solver, str):
        raise SolverError(f"compile({ocp.name}): solver must be a name (str) or None, got "
                          f"{type(solver).__name__}")
    if options is not None and not isinstance(options, dict):
        raise SolverError(f"compile({ocp.name}): options must be a dict or None, got "
                          f"{type(options).__name__}")
    if retries is not None and not (isinstance(retries, list) and all(
            isinstance(r, tuple) and len(r) == 2 and isinstance(r[0], str)
            and isinstance(r[1], dict) for r in retries)):
        raise SolverError(f"compile({ocp.name}): retries must be a list of (solver name, "
                          f"options dict) pairs or None, got {retries!r:.60}")
    if not isinstance(backend, str) or backend not in BACKENDS:
        raise SolverError(f"{ocp.name}: unknown backend {backend!r}; use one of "
                          f"{', '.join(BACKENDS)}")
    if backend == "casadi":
        return CasadiCompiled(ocp, solver or "ipopt", options, retries)
    return CvxpyCompiled(ocp, solver, options)


__all__ = ["BACKENDS", "CasadiCompiled", "Compiled", "CvxpyCompiled", "Solution", "compile"]
