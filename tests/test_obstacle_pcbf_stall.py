"""fatrop's stall stop on the §8.3 PCBF algorithm (issue #16/#14, session 14;
docs/obstacles.md "session 14"): :data:`~balustrade.reproduce.obstacles.STALL` sets
fatrop's ``tol_acceptable``/``acceptable_iter`` so that a stalled fatrop run stops as
``StopAtAcceptablePoint``. That stop must be a *failure* in Python and in the C (the chain
goes on; an acceptable point is never used as the optimum), and the options must reach the
emitted fatrop code, or C and Python would run different chains.

The behavioural test forces the stop at fatrop's first iterate (``tol_acceptable`` 1e3 held
for 1 iteration) on the short-horizon variant (N = 15): every fatrop run then fails, every
solve ends in the chain's IPOPT, in Python and in C with the same attempt counts, statuses and
inputs. Without the options in the C (or with the stop taken as a success in Python) the
attempt counts or the solvers differ."""

from __future__ import annotations

import ctypes

import numpy as np
import pytest

from balustrade.backends.stall import with_stall_stop
from balustrade.backends.targets import target as resolve
from balustrade.errors import BalustradeError
from balustrade.models.obstacle_car import obstacle_car, obstacle_setup, signed_distance
from balustrade.reproduce import obstacles as O

SHORT = 15
FORCED = (1e3, 1)  # every fatrop run stops at its first iterate


def test_stall_target_adds_the_stop_to_fatrop_targets_only():
    t = with_stall_stop("structured-ip")
    fat = t.options["fatrop"]
    assert (fat["tol_acceptable"], fat["acceptable_iter"]) == O.STALL
    assert fat["max_iter"] == 300 and fat["print_level"] == 0  # the defaults kept
    assert t.retries == resolve("structured-ip").retries
    assert with_stall_stop("exact") == "exact"
    assert with_stall_stop("structured-ip", None) == "structured-ip"
    # a user's own fatrop options are kept
    mine = resolve("structured-ip").with_options({"fatrop": {"max_iter": 50}})
    assert with_stall_stop(mine).options["fatrop"]["max_iter"] == 50


@pytest.mark.parametrize("bad", [(1e-3,), (0.0, 20), (1e-3, 0), (1e-3, 2.5), (np.nan, 20),
                                 "1e-3,20", (True, 20)])
def test_a_bad_stall_is_refused_before_any_solver_is_built(bad):
    with pytest.raises(BalustradeError, match="stall_stop"):
        O.pcbf_algorithm("structured-ip", horizon=SHORT, stall_stop=bad)


def test_the_cold_fatrop_retry_shares_the_stop():
    f = O.pcbf_algorithm("structured-ip", shifted=False, horizon=SHORT)
    for prob in (f.slack, f.filter):
        assert prob.options["fatrop"]["acceptable_iter"] == O.STALL[1]
        solvers = prob._retry_solvers()
        assert solvers[0] is prob.solver  # ("fatrop", {}): the same solver, same options


def _counted(f) -> dict[str, list]:
    """Record (problem, solver, message) of every attempt of ``f``'s two problems."""
    calls: dict[str, list] = {"slack": [], "filter": []}
    for name in calls:
        prob = getattr(f, name)
        inner = prob._solve_with

        def rec(solver, p, guess, inner=inner, name=name):
            s = inner(solver, p, guess)
            calls[name].append((s.solver, s.message))
            return s

        prob._solve_with = rec
    return calls


@pytest.fixture(scope="module")
def forced(tmp_path_factory):
    c = O.pcbf_algorithm_c("structured-ip", horizon=SHORT, stall_stop=FORCED,
                           build_dir=tmp_path_factory.mktemp("obstacle_stall"))
    py = O.pcbf_algorithm("structured-ip", shifted=False, horizon=SHORT, stall_stop=FORCED)
    return py, c


def test_a_stall_stop_is_a_failure_in_python_and_c(forced):
    """Cold steps and a braking closed loop: no fatrop attempt converges (they stop at their
    acceptable point, a few by a failed line search first), the chain's IPOPT ends every
    solve; C = Python (status, input, attempts of each problem)."""
    py, c = forced
    calls = _counted(py)
    Q = c._lib.manifest["name"]
    c_attempts = {k: c._lib.fn(f"{Q}_{k}_attempts", ctypes.c_int, [ctypes.c_void_p])
                  for k in calls}
    s, system = obstacle_setup(), obstacle_car()
    rng = np.random.default_rng(1)
    states = []
    while len(states) < 4:  # low speeds: N = 15 stops the car from v <= 1.5
        x = rng.uniform([-2, -1.5, -np.pi, 0, -0.75], [2, 1.5, np.pi, 1.0, 0.75])
        if signed_distance(x[None], s.obstacles).min() > 0.02:
            states.append((x, rng.uniform(s.U.lb, s.U.ub), True))
    x, u_p = np.array([-1.6, -0.8, 0.0, 1.0, 0.0]), np.array([2.0, 0.0])
    stopped = certified = 0
    py.reset()
    c.reset()
    for k in range(len(states) + 15):
        if k < len(states):
            xk, upk, _ = states[k]
            py.reset()
            c.reset()
        else:  # the braking loop from (−1.6, −0.8)
            xk, upk = x, u_p
        for v in calls.values():
            v.clear()
        (u1, i1), (u2, i2) = py.step(xk, upk), c.step(xk, upk)
        assert i1.status == i2.status and i1.fallback == i2.fallback, (k, i1, i2)
        np.testing.assert_allclose(u2, u1, atol=1e-8)
        for name, run in calls.items():
            if not run:
                continue
            # fatrop never answers: its acceptable stop is a failure, the chain goes on
            assert run[-1][0] == "ipopt", (k, name, run)
            assert not any(m.startswith("fatrop: Success") for _, m in run), run
            stopped += sum(m.startswith("fatrop: StopAtAcceptablePoint") for _, m in run)
            work = getattr(c, name).work
            assert c_attempts[name](work) == len(run), (k, name, run)
        certified += i1.status == "certified"
        if k >= len(states):
            x = system.step(x, u1)
    assert stopped >= 10 and certified >= 3
