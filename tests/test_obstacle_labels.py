"""Labels of the §8.3 data (Algorithm 7.6 on (2.24) with v_N = 0): a state from which the car
can stop with zero slack has h_PB = 0 and must not be labelled unsafe (audit D, session 15).

The two states are points of a sampled walk (seed 3 of audits/s15/d_obstacles_data.py)
where the solver, warm-started along the walk or cold, ended ``optimal`` at h_PB = 0.021 and
0.069. The certificate is independent of the solver: the inputs the sampler returns are
rolled out through (8.1) written here by hand and every tightened row is checked."""

from __future__ import annotations

import math

import numpy as np
import pytest

from balustrade.examples.obstacles import braking_guess, obstacle_problems
from balustrade.learn.sampler import Evaluator, Seed

STATES = ([-0.4342815701386724, -0.1500527905336022, -1.9174938620074293,
           2.8651493502713317, -0.5830097781004756],
          [-0.40648334829124444, -0.13551834304091814, -2.010942307926226,
           2.8773425594989197, -0.5824234767700455])
TS, L, N, STEP = 0.02, 0.09, 50, 1e-4
DISCS = [(ox, oy, 0.15) for ox in (-0.8, 0.0, 0.8) for oy in (-0.8, 0.0, 0.8)]


def _rows(x: list[float]) -> list[float]:
    """c_x of SPEC §2.32 by hand: r² − ‖p − o‖² per disc, then ±δ − 0.75."""
    return [r * r - (x[0] - ox) ** 2 - (x[1] - oy) ** 2 for ox, oy, r in DISCS] + \
        [x[4] - 0.75, -x[4] - 0.75]


def _zero_slack_stop(x0: list[float], u: np.ndarray) -> float:
    """The largest violation of the zero-slack (2.24) constraints along the rollout of ``u``:
    every row + Δ_i <= 0 for i < N, v_N = 0 and every row + Δ_N <= 0, u in U."""
    x, worst = list(x0), -math.inf
    for i in range(N):
        tau, dd = float(u[0, i]), float(u[1, i])
        worst = max(worst, max(_rows(x)) + STEP * i, -5 - tau, tau - 2, abs(dd) - 2.8)
        x = [x[0] + TS * x[3] * math.cos(x[2]), x[1] + TS * x[3] * math.sin(x[2]),
             x[2] + TS * x[3] / L * math.tan(x[4]), x[3] + TS * tau, x[4] + TS * dd]
    return max(worst, abs(x[3]) - 1e-7, max(_rows(x)) + STEP * N)


@pytest.fixture(scope="module")
def problems():
    return obstacle_problems()


@pytest.mark.parametrize("x", STATES)
def test_a_stoppable_state_is_labelled_inside_S_PB(problems, x):
    sample, _ = Evaluator(problems).point(np.array(x), Seed(np.array(x)))
    assert sample.ok
    u = np.asarray(sample.solutions["slack"]["u"], float).reshape(2, N)
    # the sampler's own point certifies h_PB(x) = 0 (zero slack, solver-independent check)
    assert _zero_slack_stop(x, u) <= 1e-7
    assert sample.h_pb == 0.0 and sample.in_s and sample.h <= 0.0


def test_braking_guess_stops_the_car():
    g = braking_guess(np.array(STATES[0]), N)
    assert g["x"].shape == (5, N + 1) and g["u"].shape == (2, N)
    assert abs(g["x"][3, -1]) < 1e-12 and np.all(g["u"][0] >= -5) and np.all(g["u"][1] == 0)


def test_exact_h_along_finds_the_zero_slack_stop():
    """``reproduce.obstacles.exact_h_along`` (where a learned loop leaves ``S_PB``) read
    ``h > 0`` at these states from its cold and warm solves; they are in ``S_PB``."""
    from balustrade.reproduce.obstacles import exact_h_along

    run = {"states": np.array(STATES), "start": (0.0, 0.0), "paths": ["certified"] * 2}
    (row,) = exact_h_along([run], lambda X: np.zeros(len(X))).values()
    assert row["steps_h_positive"] == 0 and row["first_step_h_positive"] is None


def test_an_inaccurate_retry_never_lowers_a_label(problems, monkeypatch):
    """The braking retry counts only when ``optimal``: an acceptable-level stop may violate
    rows, and keeping the lower value would favour it in the unsafe direction (review R3).
    The retry is made to answer ``optimal_inaccurate`` at h_PB = 0: the walk's label stays."""
    from balustrade.backends import Status

    ev = Evaluator(problems)
    x = np.array(STATES[0])
    walk = ev._solve("slack", x, Seed(x))
    assert walk.status == Status.OPTIMAL and walk.objective > 1e-3   # the local optimum
    monkeypatch.setattr(ev, "_solve", lambda which, x, seed: walk)
    real = problems.slack.solve

    def inaccurate(params, **kw):
        sol = real(params, **kw)
        sol.status, sol.objective = Status.OPTIMAL_INACCURATE, 0.0
        return sol

    monkeypatch.setattr(problems.slack, "solve", inaccurate)
    assert ev._slack(x, Seed(x)) is walk
    monkeypatch.setattr(problems.slack, "solve", real)
    assert ev._slack(x, Seed(x)).objective <= 1e-7                  # an optimal retry wins
