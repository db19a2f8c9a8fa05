"""Emitted C warm starts and the opt-in shifted-plan attempt of (2.23) (review of
session 12, issue #16).

* ``P_solve_from`` (bal/problem.c) reads the start in the work struct; a non-finite one
  (``P_warm_start`` copies the last ``x`` as it is) becomes the cold start, as
  ``CasadiCompiled._initial_guess`` does for a non-finite Solution (a NaN start made a solver
  not return); a non-finite second start is ignored.
* ``PCBFSafetyFilter(shifted_retry=...)`` → ``<name>_SHIFTED_RETRY``: off by default, so a
  certified step whose (2.23) attempt from its last solution fails runs no attempt from the
  shifted plan (Python and C attempt counts equal; one more with the option on).

The (2.23) target stops ``sqpmethod`` after one iteration, so the warm attempt fails at a
step whose start is not already optimal (measured: the 6th step from (0.2, −0.1)) and the
retry (100 iterations) converges."""

from __future__ import annotations

import ctypes

import numpy as np
import pytest
import scipy.linalg as sla

from balustrade.backends import compile
from balustrade.backends.targets import Target
from balustrade.control import PCBFSafetyFilter
from balustrade.dsl.sets import Box
from balustrade.dsl.system import LinearSystem
from balustrade.problems.pcbf import pcbf_filter_problem, pcbf_slack_problem

N = 10
A = np.array([[1.0, 0.1], [-0.4, 0.85]])
B = np.array([[0.0], [0.5]])
P = sla.solve_discrete_lyapunov(A.T, np.eye(2))
LEVEL = 0.125 / np.max(np.diag(np.linalg.inv(P)))
ONE_ITER = Target("casadi", "sqpmethod", {"lowering": "as-emitted", "max_iter": 1},
                  retries=(("sqpmethod", {"max_iter": 100}),), name="one-iteration")
STEPS = 8


@pytest.fixture(scope="module")
def pair():
    system = LinearSystem(A, B, name="stable2")
    X, U = Box([-1.0, -1.5], [1.0, 1.5]), Box([-2.0], [2.0])
    h_f, d = (lambda x: x.T @ P @ x - LEVEL), 1e-3 * np.arange(N)
    slack = compile(pcbf_slack_problem(system, X, U, h_f, N, d, 1e6, 1), "fast-sqp")
    filt = compile(pcbf_filter_problem(system, X, U, h_f, N, d, 1e-6), ONE_ITER)
    return slack, filt, U


def _python_attempts(ctl: PCBFSafetyFilter) -> list[tuple[str, int]]:
    """(status, (2.23) attempts) per step of the loop from (0.2, −0.1)."""
    out, x = [], np.array([0.2, -0.1])
    inner = ctl.filter._solve_with
    n = [0]

    def counting(solver, p, guess):
        n[0] += 1
        return inner(solver, p, guess)

    ctl.filter._solve_with = counting
    try:
        ctl.reset()
        for _ in range(STEPS):
            n[0] = 0
            u, info = ctl.step(x, np.array([0.3]))
            out.append((info.status, n[0], u.copy()))
            x = A @ x + B @ u
    finally:
        del ctl.filter._solve_with
    return out


def _c_attempts(c) -> list[tuple[str, int]]:
    Q = c._lib.manifest["name"]
    attempts = c._lib.fn(f"{Q}_filter_attempts", ctypes.c_int, [ctypes.c_void_p])
    out, x = [], np.array([0.2, -0.1])
    c.reset()
    for _ in range(STEPS):
        u, info = c.step(x, np.array([0.3]))
        ran = info.values.get("certificate_first") == 1.0 or info.fallback != "shifted_plan"
        out.append((info.status, attempts(c.filter.work) if ran else 0, u.copy()))
        x = A @ x + B @ u
    return out


@pytest.mark.parametrize("retry", [False, True])
def test_shifted_attempt_is_opt_in_c_equals_python(pair, retry, tmp_path):
    from balustrade.codegen import CPCBFSafetyFilter, build, emit_pcbf

    slack, filt, U = pair
    py = PCBFSafetyFilter(slack, filt, U) if not retry else \
        PCBFSafetyFilter(slack, filt, U, shifted_retry=True)
    emitted = emit_pcbf(py, "retrypcbf", tmp_path)
    assert emitted.manifest["shifted_retry"] is retry
    c = CPCBFSafetyFilter(build(tmp_path, emitted.name, werror=True))
    got_py, got_c = _python_attempts(py), _c_attempts(c)
    assert [s for s, _, _ in got_py] == [s for s, _, _ in got_c]
    assert [n for _, n, _ in got_py] == [n for _, n, _ in got_c]
    for (_, _, a), (_, _, b) in zip(got_py, got_c, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-6)
    # the 6th step: the warm attempt fails; the retry from the shifted plan (also one
    # iteration) fails too when on, then the 100-iteration retry converges
    assert got_py[5][0] == "certified" and got_py[5][1] == (3 if retry else 2)
