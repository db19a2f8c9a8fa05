"""The support function of a :class:`~balustrade.dsl.sets.FunctionSet` by a local NLP.

``h_S(a) = max {aᵀx : c(x) <= 0}`` needs an NLP solver, and the language (``dsl/``) names
none (issue #13, §1): the NLP lives here and :mod:`balustrade.backends` registers it as the
default of :meth:`FunctionSet.support <balustrade.dsl.sets.FunctionSet.support>` when it is
imported (:func:`~balustrade.dsl.sets_function.register_support_solver`). Exact when ``c`` is
convex; a set with a row that is not provably convex (affine or a convex quadratic) is
refused, since the local maximum would be a lower bound of the support.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from balustrade.errors import BalustradeError

#: IPOPT with its own tolerances, silent (the options FunctionSet.support always used)
_OPTIONS = {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes"}


def function_set_support(fset: object, a: np.ndarray) -> float:
    """``max {aᵀx : fset.c(x) <= 0}`` from ``x = 0`` (``a`` already checked by the caller);
    raises :class:`~balustrade.errors.BalustradeError` naming the set if the NLP fails, or
    if a row of ``c`` is not provably convex (:func:`_convex_rows`): there the NLP finds a
    local maximum, a *lower* bound of the support, and a tightening ``P ⊖ S`` or a
    containment ``S ⊆ P`` built on it is not conservative (audit B, session 14: two discs
    at x₁ = −3 and x₁ = 6 gave ``h(e₁) = −2`` instead of 7, and ``S ⊆ {x₁ <= 2}`` was
    answered ``True``)."""
    x = ca.SX.sym("x", fset.dim)
    _convex_rows(fset, x)
    solver = ca.nlpsol("support", "ipopt", {"x": x, "f": -ca.dot(ca.DM(a), x),
                                            "g": fset.c(x)}, _OPTIONS)
    res = solver(x0=np.zeros(fset.dim), ubg=0)
    if not solver.stats()["success"]:
        raise BalustradeError(f"{fset.name}.support: NLP failed "
                              f"({solver.stats()['return_status']})")
    return float(-res["f"])


def _convex_rows(fset: object, x: ca.SX) -> None:
    """Every row of ``fset.c`` affine or a convex quadratic of ``x`` (the classify pass of
    the convex backends); else a BalustradeError naming the set and the row."""
    from balustrade.backends.passes.classify import affine, quadratic
    from balustrade.errors import ConvexityError

    rows, p = ca.vec(fset.c(x)), ca.SX(0, 1)
    for j in range(rows.numel()):
        if affine(rows[j], x, p, fset.name) is not None:
            continue
        try:
            quadratic(rows[j], x, p, f"{fset.name}: row {j}")
        except ConvexityError as exc:
            raise BalustradeError(
                f"{fset.name}.support: row {j} of c(x) is not provably convex (affine or a "
                "convex quadratic), so the local NLP would give a local maximum, a lower "
                "bound of the support: tightenings and containments built on it would not "
                "be conservative. Give the set an exact support solver "
                "(FunctionSet(..., support=fn))") from exc


__all__ = ["function_set_support"]
