"""The support function of a :class:`~balustrade.dsl.sets.FunctionSet` by a local NLP.

``h_S(a) = max {aᵀx : c(x) <= 0}`` needs an NLP solver, and the language (``dsl/``) names
none (issue #13, §1): the NLP lives here and :mod:`balustrade.backends` registers it as the
default of :meth:`FunctionSet.support <balustrade.dsl.sets.FunctionSet.support>` when it is
imported (:func:`~balustrade.dsl.sets_function.register_support_solver`). Exact when ``c`` is
convex; a local maximum otherwise.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from balustrade.errors import BalustradeError

#: IPOPT with its own tolerances, silent (the options FunctionSet.support always used)
_OPTIONS = {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes"}


def function_set_support(fset: object, a: np.ndarray) -> float:
    """``max {aᵀx : fset.c(x) <= 0}`` from ``x = 0`` (``a`` already checked by the caller);
    raises :class:`~balustrade.errors.BalustradeError` naming the set if the NLP fails."""
    x = ca.SX.sym("x", fset.dim)
    solver = ca.nlpsol("support", "ipopt", {"x": x, "f": -ca.dot(ca.DM(a), x),
                                            "g": fset.c(x)}, _OPTIONS)
    res = solver(x0=np.zeros(fset.dim), ubg=0)
    if not solver.stats()["success"]:
        raise BalustradeError(f"{fset.name}.support: NLP failed "
                              f"({solver.stats()['return_status']})")
    return float(-res["f"])


__all__ = ["function_set_support"]
