"""CasADi and cvxpy agree on h_PB, h̄_PB and the filter input at 50 random states, and
every solution passes verify() (issue 2, must show)."""

from __future__ import annotations

import numpy as np
import pytest

from balustrade.testing import verify


def close(a: float, b: float, rtol: float = 1e-5, atol: float = 1e-6) -> bool:
    return abs(a - b) <= atol or abs(a - b) <= rtol * max(abs(a), abs(b))


@pytest.fixture(scope="module")
def states() -> np.ndarray:
    rng = np.random.default_rng(42)
    return rng.uniform([-1.0, -3.0], [1.0, 3.0], size=(50, 2))


def test_h_pb_and_extended_agree(pend, states):
    for x in states:
        for name in ("slack", "extended"):
            sols = {b: pend.compiled[name, b].solve({"x0": x}) for b in ("casadi", "cvxpy")}
            assert all(s.success for s in sols.values()), {b: s.summary() for b, s in sols.items()}
            a, b = sols["casadi"].objective, sols["cvxpy"].objective
            assert close(a, b), (name, x, a, b)
            ocp = pend.slack if name == "slack" else pend.extended
            for s in sols.values():
                report = verify(ocp, s, tol=1e-6)
                assert report.ok, str(report)


def test_filter_input_agrees(pend, states):
    for x in states:
        s1 = pend.compiled["slack", "cvxpy"].solve({"x0": x})
        params = {"x0": x, "u_p": np.array([2.0]), "xi": np.maximum(s1["xi"], 0.0),
                  "xi_N": max(float(s1["xi_N"][0]), 0.0)}
        sols = {b: pend.compiled["filter", b].solve(params) for b in ("casadi", "cvxpy")}
        assert all(s.success for s in sols.values())
        ua, ub = sols["casadi"]["u"][0, 0], sols["cvxpy"]["u"][0, 0]
        assert close(ua, ub), (x, ua, ub)
        for s in sols.values():
            assert verify(pend.filter, s, tol=1e-6).ok


def test_ipopt_agrees_with_cvxpy_on_h_pb(pend):
    from balustrade.backends import compile

    ipopt = compile(pend.slack, "casadi", "ipopt")
    for x in np.random.default_rng(5).uniform([-1.0, -3.0], [1.0, 3.0], size=(10, 2)):
        a = ipopt.solve({"x0": x}).objective
        b = pend.compiled["slack", "cvxpy"].solve({"x0": x}).objective
        assert close(a, b), (x, a, b)


def test_verify_detects_violations(pend):
    sol = pend.compiled["slack", "cvxpy"].solve({"x0": np.array([0.9, 0.0])})
    assert verify(pend.slack, sol).ok
    broken = sol.w.copy()
    broken[0] += 0.1  # x_{0|k} no longer equals the parameter x0
    bad = type(sol)(**{**sol.__dict__, "w": broken})
    report = verify(pend.slack, bad)
    assert not report.ok and report.block_violation["initial_state"] == pytest.approx(0.1)
    negative = sol.w.copy()
    k = pend.slack.unpack_variables(np.arange(sol.w.size, dtype=float))["xi"][0, 0]
    negative[int(k)] = -0.5  # a declared-nonnegative slack goes negative
    report = verify(pend.slack, type(sol)(**{**sol.__dict__, "w": negative}))
    assert report.bound_violation["xi"] == pytest.approx(0.5)
