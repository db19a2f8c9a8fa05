"""(2.23) of a certified step: if the attempt from its last solution fails, the certified
shifted plan (feasible for (2.23): SPEC §2.7, the rows of (2.24) with the slacks fixed to
``ξ* + eps``, here ``ξ* = 0``) is tried before the cold retries (issue #16, session 12;
:meth:`PCBFSafetyFilter._filter_solve`, ``CasadiCompiled.solve(second_start=)``,
bal/problem.c ``P_solve_from``).

A forced failure of the warm attempt counts the attempts and checks where the second one
starts; without the extra attempt the second run would be the cold retry. The attempt is
opt-in (``shifted_retry``, off by default: review of session 12, it cost 50 % more (2.23)
iterations on the cart-pole ``fast-sqp`` loop without changing a decision)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg as sla

from balustrade.backends.solution import Solution
from balustrade.control import PCBFSafetyFilter
from balustrade.dsl.sets import Box
from balustrade.dsl.system import LinearSystem

N = 10
A = np.array([[1.0, 0.1], [-0.4, 0.85]])
B = np.array([[0.0], [0.5]])
P = sla.solve_discrete_lyapunov(A.T, np.eye(2))
LEVEL = 0.125 / np.max(np.diag(np.linalg.inv(P)))


@pytest.fixture(scope="module")
def ctl() -> PCBFSafetyFilter:
    system = LinearSystem(A, B, name="stable2")
    X, U = Box([-1.0, -1.5], [1.0, 1.5]), Box([-2.0], [2.0])
    return PCBFSafetyFilter.build(system, X, U, lambda x: x.T @ P @ x - LEVEL, N,
                                  1e-3 * np.arange(N), target="structured-ip",
                                  shifted_retry=True)


def _record(compiled, fail_first: bool) -> list[tuple]:
    """Wrap ``compiled._solve_with``: record (solver, x0, p) of every attempt; the first
    one fails when ``fail_first``."""
    calls: list[tuple] = []
    inner = compiled._solve_with

    def solve_with(solver, p, guess):
        calls.append((solver, np.array(guess[0], dtype=float).reshape(-1), np.array(p)))
        if fail_first and len(calls) == 1:
            return compiled._failed(p, 0.0, "forced failure (test)")
        return inner(solver, p, guess)

    compiled._solve_with = solve_with
    return calls


def _step_recorded(ctl: PCBFSafetyFilter, x: np.ndarray, fail_first: bool):
    """One step of ``ctl`` at ``x`` with its (2.23) attempts recorded (:func:`_record`);
    returns ``(u, info, calls)``."""
    calls = _record(ctl.filter, fail_first=fail_first)
    try:
        u, info = ctl.step(x, np.array([0.3]))
    finally:
        del ctl.filter._solve_with
    return u, info, calls


def _certified_state(ctl: PCBFSafetyFilter) -> np.ndarray:
    """Run a few steps from inside the safe set until the next one is certified first with
    a last (2.23) solution; returns that next state."""
    ctl.reset()
    x = np.array([0.2, -0.1])
    for _ in range(5):
        u, info = ctl.step(x, np.array([0.3]))
        x = A @ x + B @ u
        if ctl._last_filter is not None and ctl._first(x) is not None:
            return x
    pytest.fail("no certified step with a last (2.23) solution")


def test_failed_warm_attempt_is_retried_from_the_shifted_plan(ctl, monkeypatch):
    x = _certified_state(ctl)
    cand = ctl._first(x)
    u, info, calls = _step_recorded(ctl, x, fail_first=True)
    assert info.values["certificate_first"] == 1.0
    # warm (forced failure), then the shifted plan, which converges: no cold retry
    assert len(calls) == 2
    assert calls[1][0] is ctl.filter.solver
    start = ctl.filter._initial_guess({"x": cand["x"], "u": cand["u"]}, calls[1][2])[0]
    cold = ctl.filter._initial_guess(None, calls[1][2])[0]
    np.testing.assert_allclose(calls[1][1], np.asarray(start, float).reshape(-1))
    assert not np.allclose(calls[1][1], np.asarray(cold, float).reshape(-1))
    assert info.status == "certified" and info.fallback is None
    assert np.all(np.abs(u) <= 2.0)


def test_no_extra_attempt_when_the_warm_attempt_succeeds(ctl):
    x = _certified_state(ctl)
    _, info, calls = _step_recorded(ctl, x, fail_first=False)
    assert info.status == "certified"
    assert len(calls) == 1


def test_backend_second_start_comes_before_the_cold_retries(ctl):
    """``CasadiCompiled.solve``: without ``second_start`` the failed first attempt goes
    straight to the cold retries; with it, one more run of the first solver from it."""
    x = _certified_state(ctl)
    cand = ctl._first(x)
    params = {"x0": x, "u_p": np.array([0.3]), "xi": np.zeros_like(cand["xi"]),
              "xi_N": 0.0}
    start = {"x": cand["x"], "u": cand["u"]}
    calls = _record(ctl.filter, fail_first=True)
    try:
        plain = ctl.filter.solve(params)
        n_plain = len(calls)
        calls.clear()
        second = ctl.filter.solve(params, second_start=start)
    finally:
        del ctl.filter._solve_with
    # the first attempt was warm, so the cold fatrop retry runs and succeeds
    assert isinstance(plain, Solution) and plain.success and n_plain == 2
    assert second.success and len(calls) == 2
    np.testing.assert_allclose(calls[1][1], np.asarray(
        ctl.filter._initial_guess(start, calls[1][2])[0], float).reshape(-1))



def test_default_runs_no_shifted_attempt(ctl):
    """``shifted_retry`` off (the default): a failed warm attempt goes straight to the cold
    retry, never to a run from the shifted plan."""
    off = PCBFSafetyFilter(ctl.slack, ctl.filter, ctl.U)
    assert off.shifted_retry is False and off.deployment_spec().shifted_retry is False
    x = _certified_state(off)
    cand = off._first(x)
    _, info, calls = _step_recorded(off, x, fail_first=True)
    assert info.values["certificate_first"] == 1.0
    start = off.filter._initial_guess({"x": cand["x"], "u": cand["u"]}, calls[1][2])[0]
    cold = off.filter._initial_guess(None, calls[1][2])[0]
    assert not np.allclose(calls[1][1], np.asarray(start, float).reshape(-1))
    np.testing.assert_allclose(calls[1][1], np.asarray(cold, float).reshape(-1))
