"""Bad input to the Chapter 4 API is a :class:`~balustrade.errors.BalustradeError` naming the
argument and the shapes, raised before any solver or LP runs (audit session 13, finding 3:
these cases raised numpy's ``ValueError`` or were accepted until the first step).

Property-style: hypothesis draws the wrong sizes; the 2-state toy of ``tests/conftest.py``
(``n = 2``, ``m = 1``, ``q = 2``)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from balustrade.control.rapsf import RAPSF
from balustrade.design.rapsf import check_assumption_4_11, check_rpi, robust_gain
from balustrade.dsl.sets import Box
from balustrade.errors import BalustradeError, ShapeError
from balustrade.problems.rapsf import TerminalSet, model_matrices

N = 4
FAST = settings(max_examples=25, deadline=None)
WRONG = st.integers(0, 7)            # a size; the right one is filtered out per test


@pytest.fixture(scope="module")
def toy(rapsf_toy):
    return rapsf_toy             # tests/conftest.py


@pytest.fixture(scope="module")
def ctrl(toy) -> RAPSF:
    return RAPSF(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, toy.Theta0)


def _never_solves(c: RAPSF) -> None:
    def boom(*args: object) -> None:
        raise AssertionError("a solver ran on bad input")
    c._solve = boom


@FAST
@given(size=WRONG.filter(lambda k: k != 2))
def test_step_x_of_wrong_size(ctrl: RAPSF, size: int) -> None:
    saved = ctrl._solve
    _never_solves(ctrl)
    try:
        with pytest.raises(ShapeError, match=rf"rapsf\.step: x: .*\(2,\).*\({size},\)"):
            ctrl.step(np.zeros(size), np.zeros(1))
    finally:
        ctrl._solve = saved


@FAST
@given(size=WRONG.filter(lambda k: k != 1))
def test_step_u_p_of_wrong_size(ctrl: RAPSF, size: int) -> None:
    saved = ctrl._solve
    _never_solves(ctrl)
    try:
        with pytest.raises(ShapeError, match=rf"rapsf\.step: u_p: .*\(1,\).*\({size},\)"):
            ctrl.step(np.zeros(2), np.zeros(size))
    finally:
        ctrl._solve = saved


def test_step_non_numbers_and_non_finite(ctrl: RAPSF) -> None:
    with pytest.raises(BalustradeError, match=r"rapsf\.step: x: expected a number"):
        ctrl.step("abc", np.zeros(1))
    # a NaN state stays a documented step, not an error: the backup policy (module docstring)
    ctrl.reset()
    u, info = ctrl.step(np.array([np.nan, 0.0]), np.zeros(1))
    assert info.status == "non_finite_state" and info.fallback == "backup"


@FAST
@given(dim=st.integers(1, 5).filter(lambda k: k != 2))
def test_sets_of_wrong_dimension(toy, dim: int) -> None:
    with pytest.raises(ShapeError, match=rf"rapsf: X0: expected dimension 2.*dimension {dim}"):
        RAPSF(toy.sys, Box.symmetric(1.0, dim), toy.F, toy.G, toy.W, toy.K, N, toy.Theta0)
    with pytest.raises(ShapeError, match=rf"rapsf: W: expected dimension 2.*dimension {dim}"):
        RAPSF(toy.sys, toy.X0, toy.F, toy.G, Box.symmetric(1e-3, dim), toy.K, N, toy.Theta0)


@FAST
@given(width=st.integers(1, 5).filter(lambda k: k != 2), rows=st.integers(1, 4))
def test_terminal_set_checked_when_built(toy, width: int, rows: int) -> None:
    with pytest.raises(ShapeError, match=rf"rapsf: terminal H_T: .*\(n, 2\).*\({rows}, {width}\)"):
        RAPSF(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, toy.Theta0,
              terminal=TerminalSet(np.ones((rows, width)), np.ones(rows)))
    with pytest.raises(ShapeError, match=r"rapsf: terminal h_T"):
        RAPSF(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, toy.Theta0,
              terminal=TerminalSet(np.ones((rows, 2)), np.ones(rows + 1)))


def test_terminal_set_non_finite_or_half_given(toy) -> None:
    with pytest.raises(BalustradeError, match=r"rapsf: terminal h_T: contains NaN"):
        RAPSF(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, toy.Theta0,
              terminal=TerminalSet(np.eye(2), np.array([np.nan, 1.0])))
    with pytest.raises(BalustradeError, match=r"rapsf: terminal needs both H_T and h_T"):
        RAPSF(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, toy.Theta0,
              terminal=TerminalSet(np.eye(2), None))


@FAST
@given(width=st.integers(1, 5).filter(lambda k: k != 2), count=st.integers(1, 5))
def test_vertices_of_wrong_width(toy, width: int, count: int) -> None:
    V = np.full((count, width), 0.5)
    shape = rf"\(n, 2\), got shape \({count}, {width}\)"
    with pytest.raises(ShapeError, match=r"check_rpi: vertices: expected shape " + shape):
        check_rpi(toy.X0, toy.sys, toy.K, V, toy.W)
    with pytest.raises(ShapeError, match=r"robust_gain: vertices: expected shape " + shape):
        robust_gain(toy.sys, V)
    with pytest.raises(ShapeError, match=r"check_assumption_4_11: vertices: .*" + shape):
        check_assumption_4_11(toy.sys, toy.X0, toy.W, toy.K, V, toy.F, toy.G)
    with pytest.raises(ShapeError, match=rf"model_matrices: theta: .*\(2,\).*\({width},\)"):
        model_matrices(toy.sys, np.full(width, 0.5))


def test_no_vertices(toy) -> None:
    with pytest.raises(ShapeError, match=r"check_assumption_4_11: vertices: expected at least "
                                         r"one vertex.*\(0, 2\)"):
        check_assumption_4_11(toy.sys, toy.X0, toy.W, toy.K, np.zeros((0, 2)), toy.F, toy.G)
    with pytest.raises(ShapeError, match=r"check_rpi: vertices: expected at least one"):
        check_rpi(toy.X0, toy.sys, toy.K, np.zeros((0, 2)), toy.W)
