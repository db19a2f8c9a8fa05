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
import time

import numpy as np
import pytest
import scipy.linalg as sla

from balustrade.backends import compile
from balustrade.backends.targets import Target
from balustrade.control import PCBFSafetyFilter
from balustrade.dsl.sets import Box
from balustrade.dsl.system import LinearSystem
from balustrade.examples.codegen import pendulum_pcbf_filter
from balustrade.problems.pcbf import pcbf_filter_problem, pcbf_slack_problem

N = 10
A = np.array([[1.0, 0.1], [-0.4, 0.85]])
B = np.array([[0.0], [0.5]])
P = sla.solve_discrete_lyapunov(A.T, np.eye(2))
LEVEL = 0.125 / np.max(np.diag(np.linalg.inv(P)))
ONE_ITER = Target("casadi", "sqpmethod", {"lowering": "as-emitted", "max_iter": 1},
                  retries=(("sqpmethod", {"max_iter": 100}),), name="one-iteration")
STEPS = 8


def stable2_problems() -> tuple:
    """The PCBF slack problem (2.24) on ``fast-sqp``, the filter (2.23) on :data:`ONE_ITER`, and U
    of the stable 2-state example (shared with tests/test_pcbf_second_solver.py)."""
    system = LinearSystem(A, B, name="stable2")
    X, U = Box([-1.0, -1.5], [1.0, 1.5]), Box([-2.0], [2.0])
    h_f, d = (lambda x: x.T @ P @ x - LEVEL), 1e-3 * np.arange(N)
    slack = compile(pcbf_slack_problem(system, X, U, h_f, N, d, 1e6, 1), "fast-sqp")
    filt = compile(pcbf_filter_problem(system, X, U, h_f, N, d, 1e-6), ONE_ITER)
    return slack, filt, U


@pytest.fixture(scope="module")
def pair():
    return stable2_problems()


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


def _dbl(c, n: int) -> np.ndarray:
    """The leading doubles of a problem's work struct (x0, lam_x0, lam_g0, …; bal/problem.h,
    as ``_CProblemView.warm_start`` reads them), writable."""
    return np.ctypeslib.as_array(ctypes.cast(c._work, ctypes.POINTER(ctypes.c_double)),
                                 shape=(n,))


@pytest.fixture(scope="module")
def pendulum_c(tmp_path_factory):
    """(2.23) of the pendulum PCBF filter (fast-sqp) as one emitted problem."""
    from balustrade.codegen import CProblem, build, emit_problem

    out = tmp_path_factory.mktemp("nonfinite_start")
    emitted = emit_problem(pendulum_pcbf_filter().filter, "nfstart", out)
    c = CProblem(build(out, emitted.name, werror=True))
    p = c.pack({"x0": np.array([0.1, 0.2]), "u_p": np.array([2.0]),
                "xi": np.zeros((4, 10)), "xi_N": 0.0})
    return c, p


@pytest.mark.parametrize("field", ["x0", "lam_x0", "lam_g0"])
def test_nonfinite_warm_start_is_the_cold_start(pendulum_c, field):
    """A NaN in the start → the cold start: one attempt, the cold solve's answer to the
    bit (measured without the check: the first attempt fails, the cold retry runs)."""
    c, p = pendulum_c
    nw, ng = c.info["nw"], c.info["ng"]
    attempts = c._lib.fn(f"{c.info['prefix']}_attempts", ctypes.c_int, [ctypes.c_void_p])
    status, value, _, w = c.solve_packed(p, warm=False)
    assert status == "ok" and attempts(c._work) == 1
    c._cold(c._work)
    at = {"x0": 0, "lam_x0": nw, "lam_g0": 2 * nw}[field]
    _dbl(c, 2 * nw + ng + 1)[at + 1] = np.nan
    t0 = time.perf_counter()
    status2, value2, _, w2 = c.solve_packed(p, warm=True)
    assert time.perf_counter() - t0 < 5.0
    assert status2 == "ok" and attempts(c._work) == 1
    assert value2 == value and np.array_equal(w2, w)


def test_nonfinite_second_start_is_ignored(pair, tmp_path):
    """``P_solve_from`` with a NaN second start runs as ``P_solve`` (the first attempt of
    the one-iteration target fails from a far-off finite start, then the cold retry
    converges)."""
    from balustrade.codegen import CProblem, build, emit_problem

    _, filt, _ = pair
    emitted = emit_problem(filt, "nfsecond", tmp_path)
    c = CProblem(build(tmp_path, emitted.name, werror=True))
    P, nw = c.info["prefix"], c.info["nw"]
    dp = ctypes.POINTER(ctypes.c_double)
    solve_from = c._lib.fn(f"{P}_solve_from", ctypes.c_int, [ctypes.c_void_p, dp, dp])
    attempts = c._lib.fn(f"{P}_attempts", ctypes.c_int, [ctypes.c_void_p])
    p = c.pack({"x0": np.array([0.3, -0.2]), "u_p": np.array([0.3]),
                "xi": np.zeros(filt.ocp.parameters["xi"].shape), "xi_N": 0.0})
    pp = p.ctypes.data_as(dp)
    _dbl(c, nw)[:] = 0.7
    plain = solve_from(c._work, pp, None)
    n_plain, w_plain = attempts(c._work), c.view.x.copy()
    assert n_plain == 2
    second = np.full(nw, np.nan)
    _dbl(c, nw)[:] = 0.7
    code = solve_from(c._work, pp, second.ctypes.data_as(dp))
    assert code == plain and attempts(c._work) == n_plain
    assert np.array_equal(c.view.x, w_plain)
