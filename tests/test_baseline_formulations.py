"""MPC (2.9), soft MPC (2.11), PSF (2.19) and the CBF filter (2.20) compile on both
backends, agree, and their solutions satisfy the declared model."""

from __future__ import annotations

import numpy as np
import pytest

from balustrade.dsl import Ellipsoid
from balustrade.problems.mpc import (
    cbf_filter_problem,
    mpc_problem,
    predictive_safety_filter,
    soft_mpc_problem,
)
from balustrade.testing import compare_backends, verify

TARGETS = ("exact", "cvxpy")


@pytest.fixture(scope="module")
def cases(pend):
    Xf = Ellipsoid(pend.h_f.P, name="Xf")
    Q, R, P = np.eye(2), np.eye(1), pend.h_f.P
    return {
        "mpc": (mpc_problem(pend.system, pend.X, pend.U, Xf, 10, Q, R, P), "x0"),
        "soft_mpc": (soft_mpc_problem(pend.system, pend.X, pend.U, Xf, 10, Q, R, P), "x0"),
        "psf": (predictive_safety_filter(pend.system, pend.X, pend.U, Xf, 10), "x0"),
        "cbf": (cbf_filter_problem(pend.system, pend.U, pend.h_f,
                                   lambda x: 0.01 * (pend.h_f(x) + 1)), "x"),
    }


@pytest.mark.parametrize("name", ["mpc", "soft_mpc", "psf", "cbf"])
def test_backends_agree_and_verify(pend, cases, name):
    ocp, state = cases[name]
    rng = np.random.default_rng(7)
    for x in rng.uniform([-0.3, -0.8], [0.3, 0.8], size=(5, 2)):
        params = {state: x}
        if "u_p" in ocp.parameters:
            params["u_p"] = [2.0]
        result = compare_backends(ocp, params, targets=TARGETS)
        assert result.agree(rtol=1e-5, atol=1e-6), (name, x, result.objectives)
        for sol in result.solutions.values():
            assert verify(ocp, sol).ok


def test_soft_mpc_is_exact_penalty_inside_and_feasible_outside(pend, cases):
    hard, _ = cases["mpc"]
    soft, _ = cases["soft_mpc"]
    from balustrade.backends import compile

    h, s = compile(hard, "cvxpy"), compile(soft, "cvxpy")
    inside = h.solve({"x0": [0.1, 0.2]})
    assert inside.success
    assert s.solve({"x0": [0.1, 0.2]}).objective == pytest.approx(inside.objective, rel=1e-6)
    assert not h.solve({"x0": [0.9, 0.0]}).success  # outside X: (2.9) infeasible
    outside = s.solve({"x0": [0.9, 0.0]})  # (2.11) is feasible everywhere
    assert outside.success and outside["xi_state"][0, 0] == pytest.approx(0.4, abs=1e-6)


def test_cbf_filter_decrease_holds(pend, cases):
    from balustrade.backends import compile

    ocp, _ = cases["cbf"]
    c = compile(ocp, "cvxpy")
    for x in np.random.default_rng(3).uniform([-0.2, -0.5], [0.2, 0.5], size=(10, 2)):
        sol = c.solve({"x": x, "u_p": [3.0]})
        x_next = pend.system.step(x, sol["u"])
        assert pend.h_f(x_next) - pend.h_f(x) <= -0.01 * (pend.h_f(x) + 1) + 1e-7
