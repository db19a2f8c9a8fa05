"""Which solver makes the shifted-plan attempt of a certified step's (2.23) (issue #16,
session 13): ``PCBFSafetyFilter(shifted_retry_solver=k)`` → ``CasadiCompiled.solve(
second_solver=k)`` → ``<name>_filter_SECOND_SOLVER`` in the emitted C (bal/problem.c
``P_solve_from``). 0 (the default) is session 12's attempt by the first solver; ``-1`` the
chain's last solver (on the obstacle car of §8.3 IPOPT, which converges from the plan where
fatrop stalls: docs/obstacles.md "session 13").

The (2.23) target of the fast tests stops ``sqpmethod`` after one iteration and retries
with 100: the warm attempt fails at the 6th step from (0.2, −0.1) (measured in
tests/test_c_nonfinite_start.py). With the first solver the attempt from the plan (one
iteration) fails too and the cold retry converges (3 attempts); with the last solver the
attempt from the plan converges (2 attempts), in Python and in C, with the same inputs."""

from __future__ import annotations

import ctypes

import numpy as np
import pytest

# the stable 2-state example of the non-finite-start tests (N, A, B, P, LEVEL, ONE_ITER, STEPS)
from test_c_nonfinite_start import (
    LEVEL,
    STEPS,
    A,
    B,
    N,
    P,
    stable2_problems,
)

from balustrade.backends import compile
from balustrade.backends.casadi_backend import chain_solver_index
from balustrade.control import PCBFSafetyFilter
from balustrade.dsl.sets import Box
from balustrade.dsl.system import LinearSystem
from balustrade.errors import BalustradeError
from balustrade.problems.pcbf import pcbf_filter_problem

FAILING_STEP = 5  # the 6th step: the warm attempt (one iteration) does not converge


@pytest.fixture(scope="module")
def pair():
    return stable2_problems()


def _python_loop(ctl: PCBFSafetyFilter) -> list[tuple]:
    """(status, fallback, (2.23) attempts as (solver object, start), u) per step of the
    loop from (0.2, −0.1)."""
    out, x = [], np.array([0.2, -0.1])
    inner = ctl.filter._solve_with
    calls: list[tuple] = []

    def recording(solver, p, guess):
        calls.append((solver, np.array(guess[0], dtype=float).reshape(-1)))
        return inner(solver, p, guess)

    ctl.filter._solve_with = recording
    try:
        ctl.reset()
        for _ in range(STEPS):
            calls.clear()
            u, info = ctl.step(x, np.array([0.3]))
            out.append((info.status, info.fallback, list(calls), u.copy()))
            x = A @ x + B @ u
    finally:
        del ctl.filter._solve_with
    return out


def test_last_solver_makes_the_shifted_plan_attempt(pair):
    slack, filt, U = pair
    first = _python_loop(PCBFSafetyFilter(slack, filt, U, shifted_retry=True))
    last = _python_loop(PCBFSafetyFilter(slack, filt, U, shifted_retry=True,
                                         shifted_retry_solver=-1))
    retry = filt._retry_solvers()[-1]
    st, fb, calls, _ = first[FAILING_STEP]
    assert st == "certified" and fb is None
    # session 12's order: warm (fails), first solver from the plan (fails), cold retry
    assert [c[0] for c in calls] == [filt.solver, filt.solver, retry]
    st, fb, calls, _ = last[FAILING_STEP]
    assert st == "certified" and fb is None
    # the last solver from the plan converges: no cold retry
    assert [c[0] for c in calls] == [filt.solver, retry]
    np.testing.assert_allclose(calls[1][1], first[FAILING_STEP][2][1][1])  # the plan
    assert not np.allclose(calls[1][1], np.asarray(filt._initial_guess(
        None, np.zeros(filt.ocp.parameter_layout.size))[0], float).reshape(-1))
    # every step stays a successful one
    assert all(s in ("ok", "certified") for s, _, _, _ in last)


def test_index_of_the_chain_is_checked(pair):
    slack, filt, U = pair
    assert chain_solver_index(-1, 2) == 2 and chain_solver_index(0, 2) == 0
    assert chain_solver_index(1, 1) == 1 and chain_solver_index(-1, 0) == 0
    for bad in (3, -2, True, 1.0):
        with pytest.raises(BalustradeError):
            chain_solver_index(bad, 2)
    for bad in (-2, True, "last"):
        with pytest.raises(BalustradeError, match="shifted_retry_solver"):
            PCBFSafetyFilter(slack, filt, U, shifted_retry=True, shifted_retry_solver=bad)
    with pytest.raises(BalustradeError, match="outside the chain"):
        filt.solve({"x0": np.zeros(2), "u_p": np.zeros(1), "xi": np.zeros((4, N)),
                    "xi_N": 0.0}, second_start={}, second_solver=2)
    assert PCBFSafetyFilter(slack, filt, U).deployment_spec().shifted_retry_solver == 0


def _c_loop(c) -> list[tuple]:
    Q = c._lib.manifest["name"]
    attempts = c._lib.fn(f"{Q}_filter_attempts", ctypes.c_int, [ctypes.c_void_p])
    out, x = [], np.array([0.2, -0.1])
    c.reset()
    for _ in range(STEPS):
        u, info = c.step(x, np.array([0.3]))
        out.append((info.status, info.fallback, attempts(c.filter.work), u.copy()))
        x = A @ x + B @ u
    return out


@pytest.mark.parametrize("which", [0, -1])
def test_c_equals_python(pair, which, tmp_path):
    """The emitted step runs the same attempts: statuses, fallbacks, attempt counts and
    inputs equal Python's; the manifest and the config name the resolved attempt."""
    from balustrade.codegen import CPCBFSafetyFilter, build, emit_pcbf

    slack, filt, U = pair
    py = PCBFSafetyFilter(slack, filt, U, shifted_retry=True, shifted_retry_solver=which)
    emitted = emit_pcbf(py, "secondpcbf", tmp_path)
    k = 0 if which == 0 else 1
    assert emitted.manifest["shifted_retry_solver"] == k
    config = (tmp_path / "secondpcbf_config.h").read_text()
    assert f"#define secondpcbf_filter_SECOND_SOLVER {k}" in config
    c = CPCBFSafetyFilter(build(tmp_path, emitted.name, werror=True))
    got_py, got_c = _python_loop(py), _c_loop(c)
    assert [(s, f) for s, f, _, _ in got_py] == [(s, f) for s, f, _, _ in got_c]
    assert [len(a) for _, _, a, _ in got_py] == [n for _, _, n, _ in got_c]
    assert got_c[FAILING_STEP][2] == (3 if which == 0 else 2)
    for (_, _, _, a), (_, _, _, b) in zip(got_py, got_c, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-6)


def test_emit_on_fast_sqp_whose_c_drops_the_ipopt_retry(pair, tmp_path):
    """``fast-sqp``'s C runs its SQP retry but not its IPOPT one (self-contained C): a
    second start by the first solver (the default) or by the SQP retry is emitted with the
    same attempt in C; the last (IPOPT, not emitted) is refused by name (session 13 review:
    any ``shifted_retry`` PCBF on ``fast-sqp`` was refused)."""
    from balustrade.codegen import emit_pcbf
    from balustrade.errors import CodegenError

    slack, _, U = pair
    system = LinearSystem(A, B, name="stable2")
    X = Box([-1.0, -1.5], [1.0, 1.5])
    filt = compile(pcbf_filter_problem(system, X, U, lambda x: x.T @ P @ x - LEVEL, N,
                                       1e-3 * np.arange(N), 1e-6), "fast-sqp")
    assert [name for name, _ in filt.retries] == ["sqpmethod", "ipopt"]
    for which, k in ((0, 0), (1, 1)):
        py = PCBFSafetyFilter(slack, filt, U, shifted_retry=True, shifted_retry_solver=which)
        emitted = emit_pcbf(py, f"fsqp{k}", tmp_path / str(k))
        assert emitted.manifest["shifted_retry_solver"] == k
        assert f"#define fsqp{k}_filter_SECOND_SOLVER {k}" in (
            tmp_path / str(k) / f"fsqp{k}_config.h").read_text()
    py = PCBFSafetyFilter(slack, filt, U, shifted_retry=True, shifted_retry_solver=-1)
    with pytest.raises(CodegenError, match="retry 2 .ipopt., whose C is not emitted"):
        emit_pcbf(py, "fsqplast", tmp_path / "last")


def test_index_past_the_chain_is_refused_at_construction(pair):
    """An attempt index past the (2.23) chain is bad input of the constructor, naming the
    argument (session 13 review: it passed ``>= -1`` and raised inside ``step()``)."""
    slack, filt, U = pair
    assert len(filt.retries) == 1
    for ok in (0, 1, -1):
        PCBFSafetyFilter(slack, filt, U, shifted_retry=True, shifted_retry_solver=ok)
    with pytest.raises(BalustradeError, match="shifted_retry_solver 2 names no attempt"):
        PCBFSafetyFilter(slack, filt, U, shifted_retry=True, shifted_retry_solver=2)
