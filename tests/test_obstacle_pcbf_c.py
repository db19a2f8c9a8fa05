"""The exact PCBF algorithm of §8.3 ((2.24) then (2.23), nine discs, ``v_N = 0``) as
emitted C on ``structured-ip`` (fatrop on the stage-ordered NLP; issue #16, session 12):
C = Python (statuses, fallbacks, inputs) and the car stays outside the discs.

Fast: a short-horizon variant (N = 15, which stops the car only from low speeds) built
through :func:`~balustrade.reproduce.obstacles.pcbf_algorithm_c`: cold steps at random
states and a closed loop. Slow: the thesis' N = 50 on one reference closed loop (the naive
MPC (8.2) proposing, 70 steps) with the minimum signed distance."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from balustrade.codegen.build import run_under_valgrind
from balustrade.models.obstacle_car import obstacle_car, obstacle_setup, signed_distance
from balustrade.reproduce import obstacles as O

SHORT = 15
TARGET = "structured-ip"


def same_status(py: str, c: str) -> bool:
    """The step statuses agree. One known difference: where Python's chain ends with IPOPT
    reporting ``Infeasible_Problem_Detected`` (status ``infeasible``), the emitted C only
    learns that the solve did not converge (CasADi's generated IPOPT code returns the same
    flag for every failure): ``…_infeasible`` in Python is ``…_not_converged`` in C."""
    return py == c or (py.endswith("infeasible")
                       and c == py[: -len("infeasible")] + "not_converged")


@pytest.fixture(scope="module")
def short(tmp_path_factory):
    c = O.pcbf_algorithm_c(TARGET, horizon=SHORT,
                           build_dir=tmp_path_factory.mktemp("obstacle_pcbf_c"))
    return O.pcbf_algorithm(TARGET, shifted=False, horizon=SHORT), c


def test_the_slack_problem_is_staged_as_a_permutation(short):
    """The fixed ``ξ_N`` (in no row, not in the cost) is a control of stage 0, not 51
    lifted copies: the emitted step maps a permutation of the layout."""
    m = short[1]._lib.manifest["problems"]["slack"]
    take = np.asarray(m["take"])
    assert m["solver"] == "fatrop"
    assert sorted(take) == list(range(m["nw"]))


def _cold_steps(short, n: int, seed: int) -> int:
    """``n`` cold steps (both filters reset) at random low-speed states outside the discs:
    C = Python (statuses, fallbacks, inputs within 1e-8); the number of "ok" steps."""
    py, c = short
    s = obstacle_setup()
    rng = np.random.default_rng(seed)
    solved = 0
    for _ in range(n):
        while True:  # low speeds: N = 15 steps of 0.02 s stop the car from v <= 1.5
            x = rng.uniform([-2, -1.5, -np.pi, 0, -0.75], [2, 1.5, np.pi, 1.0, 0.75])
            if signed_distance(x[None], s.obstacles).min() > 0.02:
                break
        u_p = rng.uniform(s.U.lb, s.U.ub)
        py.reset()
        c.reset()
        (u1, i1), (u2, i2) = py.step(x, u_p), c.step(x, u_p)
        assert same_status(i1.status, i2.status), (i1.status, i2.status)
        assert i1.fallback == i2.fallback
        np.testing.assert_allclose(u2, u1, atol=1e-8)
        solved += i1.status == "ok"
    return solved


def test_cold_steps_c_equals_python(short):
    assert _cold_steps(short, 15, 0) >= 10


@pytest.mark.slow
def test_1000_cold_steps_c_equals_python(short):
    """The must-show of issue #14 for the obstacle PCBF's C: 1000 states (audit C,
    session 14)."""
    assert _cold_steps(short, 1000, 14) >= 500


def test_closed_loop_c_equals_python_and_avoids_the_disc(short):
    """Speeding up towards the disc at (−0.8, −0.8): the filter brakes; C and Python take
    the same steps (status, input) and the car stays outside every disc."""
    py, c = short
    system, s = obstacle_car(), obstacle_setup()
    x0 = np.array([-1.6, -0.8, 0.0, 1.0, 0.0])
    u_p = np.array([2.0, 0.0])
    xs = {"py": [x0], "c": [x0]}
    py.reset()
    c.reset()
    statuses = []
    for _ in range(30):
        (u1, i1), (u2, i2) = py.step(xs["py"][-1], u_p), c.step(xs["c"][-1], u_p)
        assert same_status(i1.status, i2.status), (i1.status, i2.status)
        np.testing.assert_allclose(u2, u1, atol=1e-8)
        statuses.append(i1.status)
        xs["py"].append(system.step(xs["py"][-1], u1))
        xs["c"].append(system.step(xs["c"][-1], u2))
    X = np.array(xs["py"])
    np.testing.assert_allclose(np.array(xs["c"]), X, atol=1e-8)
    assert signed_distance(X, s.obstacles).min() >= O.SAFE_TOL
    assert X[-1, 3] < 0.5  # braked in front of the disc, not through it
    assert "certified" in statuses  # the shifted-plan certificate ran in both


@pytest.mark.slow
def test_reference_loop_c_equals_python(tmp_path):
    """N = 50, start (−1.8, −1.0), 70 steps, the Python and C filters as two interleaved
    closed loops: the same statuses and inputs, min signed distance >= −1e-3 (measured
    +0.00066 m, as the IPOPT loops)."""
    from benchmarks.obstacles_pcbf_c import build_pair, lockstep_loops

    pair = build_pair(TARGET, tmp_path)
    res = lockstep_loops(pair["py"], pair["c"], starts=(O.STARTS[0],), steps=O.STEPS)
    assert res["max_du"] <= 1e-8 and res["max_dx"] <= 1e-8
    assert all(same_status(a, b) for _, _, a, b in res["status_differs"])
    assert res["min_distance_py"] >= O.SAFE_TOL and res["min_distance_c"] >= O.SAFE_TOL


@pytest.mark.slow
def test_shifted_plan_attempt_c_equals_python(tmp_path):
    """From (1.5, −1.5) (N = 50, the naive MPC proposing) steps 39–41 are certified steps
    whose (2.23) attempt from its last solution fails and the attempt from the shifted plan
    converges (``shifted_retry``, on for this car; review of session 12): C = Python in
    statuses, fallbacks, inputs and (2.23) attempt counts at every step up to 42."""
    import ctypes

    from benchmarks.obstacles_pcbf_c import build_pair

    pair = build_pair(TARGET, tmp_path)
    py, c = pair["py"], pair["c"]
    assert py.shifted_retry and c._lib.manifest["shifted_retry"]
    q = c._lib.manifest["name"]
    c_attempts = c._lib.fn(f"{q}_filter_attempts", ctypes.c_int, [ctypes.c_void_p])
    inner, n = py.filter._solve_with, [0]

    def counting(solver, p, guess):
        n[0] += 1
        return inner(solver, p, guess)

    py.filter._solve_with = counting
    plant = obstacle_car()
    x0 = O.initial_state((1.5, -1.5))
    xs, mpcs = {"py": x0.copy(), "c": x0.copy()}, {"py": O.NaiveMPC(), "c": O.NaiveMPC()}
    for m in mpcs.values():
        m.start(x0)
    py.reset()
    c.reset()
    counts = []
    try:
        for step in range(42):
            n[0] = 0
            u1, i1 = py.step(xs["py"], mpcs["py"](step, xs["py"]))
            u2, i2 = c.step(xs["c"], mpcs["c"](step, xs["c"]))
            assert same_status(i1.status, i2.status), (step, i1.status, i2.status)
            assert i1.fallback == i2.fallback
            np.testing.assert_allclose(u2, u1, atol=1e-8)
            if "filter" in i1.solutions:
                assert c_attempts(c.filter.work) == n[0], step
            counts.append(n[0])
            xs = {"py": plant.step(xs["py"], u1), "c": plant.step(xs["c"], u2)}
    finally:
        del py.filter._solve_with
    assert counts[39:42] == [2, 2, 2]  # warm attempt failed, the shifted plan converged


DRIVER = r"""
/* Replays the states and proposals of a Python closed loop through the emitted step. */
#include <stdio.h>
#include "obstacles_pcbf_n15.h"
#include "replay.h"

int main(void) {
  obstacles_pcbf_n15_work* wk = obstacles_pcbf_n15_alloc();
  casadi_real u[obstacles_pcbf_n15_NU], h;
  int k, st;
  if (!wk) return 1;
  for (k = 0; k < REPLAY_K; ++k) {
    obstacles_pcbf_n15_step(REPLAY_X[k], REPLAY_U, u, &h, &st, wk);
    printf("%d %.17g %.17g\n", st, u[0], u[1]);
  }
  obstacles_pcbf_n15_free(wk);
  return 0;
}
"""


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("valgrind") is None, reason="needs valgrind")
def test_replayed_loop_is_memory_clean_under_valgrind(short):
    """The braking loop of the N = 15 variant (12 steps, certified and solved steps) replayed
    through the emitted C by a driver without Python, under valgrind (fatrop, its cold
    retry and IPOPT linked): no memory error, no definite leak, the inputs of Python within
    1e-8 (audit C, session 14: the obstacle PCBF had no memcheck run)."""
    from balustrade.codegen import build_executable

    py, c = short
    system = obstacle_car()
    x, u_p = np.array([-1.6, -0.8, 0.0, 1.0, 0.0]), np.array([2.0, 0.0])
    py.reset()
    xs, us = [], []
    for _ in range(12):
        u, _ = py.step(x, u_p)
        xs.append(x)
        us.append(u)
        x = system.step(x, u)
    out = c.accelerated["dir"]
    rows = ",\n".join("{" + ", ".join(f"{v:.17g}" for v in r) + "}" for r in xs)
    (out / "replay.h").write_text(
        f"#define REPLAY_K {len(xs)}\nstatic const casadi_real REPLAY_X[{len(xs)}][5] = "
        f"{{{rows}}};\nstatic const casadi_real REPLAY_U[2] = {{2.0, 0.0}};\n")
    (out / "driver.c").write_text(DRIVER)
    flags = tuple(c._lib.manifest["link_flags"])
    exe = build_executable(out, main="driver.c", werror=True, extra_flags=flags,
                           out=out.parent / "obstacle_driver")
    proc = run_under_valgrind(str(exe), timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    u_c = np.array([[float(v) for v in line.split()[1:]] for line in proc.stdout.splitlines()])
    np.testing.assert_allclose(u_c, np.array(us), atol=1e-8)
