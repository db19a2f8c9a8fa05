"""Offline design of ellipsoidal RPI error sets (Assumption 5.13, SPEC §1.11): solve the SDP
(5.14) of :mod:`balustrade.problems.rpi` on a synthesis target over a line search in ``λ``.

The formulation lives in ``problems/`` (language only); the solves live here.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

from balustrade.backends import compile_synthesis
from balustrade.dsl.error_sets import ErrorSet
from balustrade.dsl.sets import Ellipsoid, Polytope, Set
from balustrade.errors import BalustradeError
from balustrade.problems.rpi import rpi_sdp


def ellipsoidal_rpi(A: np.ndarray, B: np.ndarray, W: Set, X: Polytope, U: Polytope,
                    G: np.ndarray | None = None, lambdas: Sequence[float] | None = None,
                    target: object = "sdp", name: str = "E") -> ErrorSet:
    """Ellipsoidal RPI set and error feedback: :func:`rpi_sdp` compiled once and solved for
    each ``λ`` of the line search (default 19 values in ``(0, 1)``), keeping the best.

    Returns ``ErrorSet(Ellipsoid(E_P⁻¹), K = Y E_P⁻¹)`` with the objective, the chosen ``λ``
    and the solve time in ``info``. ``target``: a synthesis target (preset ``"sdp"``)."""
    lambdas = list(lambdas) if lambdas is not None else list(np.linspace(0.05, 0.95, 19))
    for lv in lambdas:
        if not 0 < lv < 1:
            raise BalustradeError(f"ellipsoidal_rpi: lambdas: every λ must lie in (0, 1), "
                                  f"got {lv}")
    compiled = compile_synthesis(rpi_sdp(A, B, W, X, U, G), target)
    best = None
    start = time.perf_counter()
    for lv in lambdas:
        sol = compiled.solve({"lambda": lv})
        if sol.ok and (best is None or sol.objective < best[0].objective):
            best = (sol, lv)
    elapsed = time.perf_counter() - start
    if best is None:
        raise BalustradeError("RPI SDP: no λ in the line search admits an ellipsoidal RPI set "
                              f"(tried {len(lambdas)} values); the system may not be "
                              "stabilizable against W")
    sol, lv = best
    Ev = 0.5 * (sol["E"] + sol["E"].T)
    P = np.linalg.inv(Ev)
    P = 0.5 * (P + P.T)
    K = sol["Y"] @ P
    return ErrorSet(Ellipsoid(P, name=name), K,
                    info={"objective": sol.objective, "lambda": lv, "solve_time": elapsed,
                          "method": "ellipsoidal SDP (SPEC §1.11)"})


__all__ = ["ellipsoidal_rpi"]
