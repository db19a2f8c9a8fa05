"""Bad input to the §8.2/§8.3 models, designs, checks and reproductions (audit D, session
15): a BalustradeError naming the argument before anything is evaluated, never a numpy or
CasADi exception and never a silent wrong answer. Each case failed on the code before the
audit (an IndexError, ValueError, CasADi assertion, or a value computed from the wrong data)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from balustrade.design.incremental_rpi import (
    TerminalSpec,
    sampled_rpi_check,
    sampled_terminal_check,
    worst_case_rpi_check,
)
from balustrade.dsl.error_sets import ErrorSet
from balustrade.dsl.sets import Box, Ellipsoid
from balustrade.errors import BalustradeError
from balustrade.examples.bicycle import bicycle_design
from balustrade.models.bicycle import ShiftedCBF, bicycle, bicycle_sets, jacobian_ldi
from balustrade.models.obstacle_car import (
    grid_obstacles,
    obstacle_car,
    obstacle_setup,
    signed_distance,
    symmetries,
)
from balustrade.problems.obstacles import naive_mpc_problem


def test_signed_distance_equals_hand_computation_and_refuses_one_column():
    P = np.array([[0.8, 0.1, 9.0, 9.0, 9.0], [-1.9, 1.4, 0, 0, 0]])
    want = [[math.hypot(p[0] - o[0], p[1] - o[1]) - o[2] for o in grid_obstacles()]
            for p in P]
    assert np.allclose(signed_distance(P), want, atol=1e-15)
    assert np.allclose(signed_distance(P[0]), want[:1], atol=1e-15)   # one 1-D state
    # an (n, 1) array used to be broadcast as (p_x, p_x): distances of other points
    with pytest.raises(BalustradeError, match="signed_distance: positions"):
        signed_distance(P[:, :1])
    with pytest.raises(BalustradeError, match="signed_distance: obstacles"):
        signed_distance(P, grid_obstacles()[:, :2])
    with pytest.raises(BalustradeError, match="symmetries: X"):
        symmetries(np.zeros((2, 3)))


@pytest.mark.parametrize("make", [lambda: obstacle_car(ts=-0.02),
                                  lambda: obstacle_car(wheelbase=0.0),
                                  lambda: bicycle(ts=0.0),
                                  lambda: bicycle(wheelbase=-0.09)])
def test_models_refuse_nonpositive_step_and_wheelbase(make):
    with pytest.raises(BalustradeError, match="ts|wheelbase"):
        make()


def test_obstacle_starts_must_be_finite_points_of_the_arena():
    from balustrade.reproduce import obstacles as O

    x = O.initial_state((-2.0, 0.5))                      # on the border: allowed
    assert np.allclose(x, [-2.0, 0.5, math.atan2(-0.5, 2.0), 3.0, 0.0])
    for p in ((5.0, 5.0), (-2.01, 0.0), (float("nan"), 0.0), (1.0,)):
        with pytest.raises(BalustradeError, match="initial position"):
            O.initial_state(p)

    class Untouched:  # a bad start is refused before any closed loop runs
        def __getattr__(self, name):
            raise AssertionError(f"used {name}")

    with pytest.raises(BalustradeError, match="outside the arena"):
        O.closed_loops(Untouched(), Untouched(), starts=((-1.8, -1.0), (0.0, 3.0)))


def test_naive_mpc_refuses_state_indices_past_the_state():
    U = obstacle_setup().U
    with pytest.raises(BalustradeError, match=r"position\[1\]"):
        naive_mpc_problem(obstacle_car(), U, position=(0, 9))
    with pytest.raises(BalustradeError, match="speed_index"):
        naive_mpc_problem(obstacle_car(), U, speed_index=5)


@pytest.mark.parametrize("kwargs, word", [({"N": 0}, "horizon"), ({"N": 2.5}, "horizon"),
                                          ({"delta_step": 0.0}, "delta_step")])
def test_bicycle_design_checks_its_arguments_before_solving(kwargs, word):
    with pytest.raises(BalustradeError, match=word):
        bicycle_design(**kwargs)


def test_bicycle_jacobian_bound_and_terminal_cbf_check_shapes():
    with pytest.raises(BalustradeError, match="jacobian_ldi: lb"):
        jacobian_ldi(np.zeros(3), np.ones(3))
    cbf = ShiftedCBF(np.eye(4), np.zeros((2, 4)), np.array([0.0, 0.0, 1.1, 0.0]), 1.0)
    assert cbf(np.array([1.0, 0.0, 1.1, 0.0])) == pytest.approx(0.0)
    with pytest.raises(BalustradeError, match="ShiftedCBF: x"):
        cbf(np.zeros(1))     # used to broadcast against x_s


def _small_error() -> tuple:
    X, U, W = bicycle_sets()
    return bicycle(), ErrorSet(Ellipsoid(np.eye(4) * 1e4), np.zeros((2, 4))), X, U, W


def test_invariance_checks_refuse_empty_counts_and_wrong_dimensions():
    system, error, X, U, W = _small_error()
    with pytest.raises(BalustradeError, match="samples"):
        sampled_rpi_check(system, error, X, U, W, samples=0)
    with pytest.raises(BalustradeError, match="starts"):
        worst_case_rpi_check(system, error, X, U, W, starts=0)
    with pytest.raises(BalustradeError, match="Z has dimension 2"):
        sampled_rpi_check(system, error, Box(U.lb, U.ub), U, W, samples=10)
    spec = TerminalSpec(np.eye(4), np.zeros((2, 4)), np.array([0, 0, 1.1, 0.0]), X, U)
    with pytest.raises(BalustradeError, match="samples"):
        sampled_terminal_check(system, spec, samples=0)
    bad = TerminalSpec(np.eye(3), np.zeros((2, 4)), np.array([0, 0, 1.1, 0.0]), X, U)
    with pytest.raises(BalustradeError, match=r"spec.P must have shape \(4, 4\)"):
        sampled_terminal_check(system, bad, samples=10)
    # well-formed arguments still run (the check itself is tested in test_lane_change)
    assert sampled_rpi_check(system, error, X, U, W, samples=8).count == 8
