"""The direct engines hand only changed data to the solver (Clarabel's ``q`` is skipped when
unchanged): a sequence of solves with changing and repeated costs must give the answers of
the cvxpy backend (history independence, issue #12 item 3)."""

from __future__ import annotations

import numpy as np
import pytest

from balustrade.backends import compile
from balustrade.dsl.costs import norm
from balustrade.dsl.ocp import OCP


def _cone_with_parametric_cost() -> OCP:
    """min cᵀu + ‖u‖₂ over a box: ``q`` depends on the parameter ``c``."""
    ocp = OCP(name="param_cost")
    u = ocp.variable("u", 2, lb=-1.0, ub=1.0)
    c = ocp.parameter("c", 2)
    ocp.le(u[0] + u[1] - 1.0, 0, name="sum")
    ocp.minimize(c[0] * u[0] + c[1] * u[1] + norm(u, 2))
    return ocp


@pytest.mark.parametrize("target", ["fast-convex", "fast-convex-qp", "fast-convex-conic"])
def test_changing_and_repeated_costs_match_cvxpy(target):
    ocp = _cone_with_parametric_cost() if target == "fast-convex" else None
    if ocp is None:                          # an LP/QP for PIQP and Clarabel-on-QP
        ocp = OCP(name="param_qp")
        u = ocp.variable("u", 2, lb=-1.0, ub=1.0)
        c = ocp.parameter("c", 2)
        ocp.minimize(c[0] * u[0] + c[1] * u[1] + u[0] ** 2 + u[1] ** 2)
    compiled, reference = compile(ocp, target), compile(ocp, "cvxpy")
    costs = [np.array([3.0, -3.0]), np.array([3.0, -3.0]), np.array([-3.0, 0.5]),
             np.array([3.0, -3.0]), np.array([0.0, 0.0]), np.array([-3.0, 0.5])]
    for c in costs:
        sol = compiled.solve({"c": c})
        ref = reference.solve({"c": c})
        assert sol.status == ref.status == "optimal", (c, sol.summary())
        assert np.allclose(sol.w, ref.w, atol=1e-6), (c, sol.w, ref.w)
        assert sol.objective == pytest.approx(ref.objective, abs=1e-7)
