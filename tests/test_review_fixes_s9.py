"""Review fixes of issue #15 (session 9): bad ``shared`` row maps of (4.5) are rejected,
``JointPolytope``/``joint_constraint`` reject non-numeric ``h``/``alpha`` and a negative
constant ``alpha`` with a :class:`BalustradeError`, a failing ``h_rows`` of
:class:`GridPCBFFilter` is wrapped, and ``support_rows`` is the dsl's ``row_supports``."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from balustrade.control.approximate import GridPCBFFilter
from balustrade.dsl import OCP, Box, JointPolytope, LinearSystem
from balustrade.errors import BalustradeError
from balustrade.models.pendulum import pendulum, pendulum_setup
from balustrade.problems.rapsf import (
    rapsf_problem,
    row_dependence,
    shared_rows,
    support_rows,
)

N = 4


@pytest.fixture(scope="module")
def toy(rapsf_toy):
    return rapsf_toy             # tests/conftest.py


def _build(toy, shared):
    return rapsf_problem(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, n_vertices=4,
                         shared=shared)


# -- 1. shared ----------------------------------------------------------------------------------
def test_valid_shared_is_accepted(toy) -> None:
    rep = shared_rows(row_dependence(toy.sys, toy.X0), toy.V.T)
    _build(toy, rep)
    rep[0] = [0, 0, 2, 2]                             # a structurally valid sharing
    rep[1] = [0, 1, 0, 1]
    _build(toy, rep)
    _build(toy, rep.astype(float))                              # integral floats are fine


@pytest.mark.parametrize("kind", ["later", "negative", "out_of_range", "chain", "fraction"])
def test_bad_shared_names_argument_entry_and_shape(toy, kind: str) -> None:
    n_X = toy.X0.H.shape[0]
    rep = np.tile(np.arange(4), (n_X, 1))
    if kind == "later":
        rep[1, 1] = 3
    elif kind == "negative":
        rep[1, 2] = -1
    elif kind == "out_of_range":
        rep[1, 3] = 7
    elif kind == "chain":                          # 2 → 1 but 1 is not its own representative
        rep[1, 1], rep[1, 2] = 0, 1
    else:
        rep = rep.astype(float)
        rep[1, 2] = 1.5
    with pytest.raises(BalustradeError, match=r"shared") as err:
        _build(toy, rep)
    if kind != "fraction":
        where = {"later": "(1, 1)", "negative": "(1, 2)", "out_of_range": "(1, 3)",
                 "chain": "(1, 2)"}[kind]
        assert where in str(err.value) and f"({n_X}, 4)" in str(err.value)


# -- 2. JointPolytope h, joint_constraint alpha -------------------------------------------------
def test_joint_polytope_non_numeric_h() -> None:
    with pytest.raises(BalustradeError, match="h"):
        JointPolytope(np.eye(2), np.ones((2, 1)), h="ab")
    with pytest.raises(BalustradeError, match="h"):
        JointPolytope(np.eye(2), np.ones((2, 1)), h=[1.0, "x"])


def test_tube_alpha_checked(toy) -> None:
    ocp = OCP(LinearSystem(np.eye(2), np.ones((2, 1))), 3, name="o")
    Z = JointPolytope(toy.F, toy.G)
    with pytest.raises(BalustradeError, match="alpha"):
        ocp.joint_constraint(Z, feedback=toy.K, tube=("a", toy.X0))
    with pytest.raises(BalustradeError, match="alpha"):
        ocp.joint_constraint(Z, feedback=toy.K, tube=(np.array([1.0, -0.5, 1.0]), toy.X0))
    with pytest.raises(BalustradeError, match="alpha"):
        ocp.joint_constraint(Z, feedback=toy.K, tube=(-1.0 * np.ones(3), toy.X0))
    assert not [b for b in ocp.blocks if b.tag == "state"]       # nothing half-added
    a = ca.SX.sym("a", 1, 3)                                      # symbolic: sign not known
    ocp.joint_constraint(Z, feedback=toy.K, tube=(a, toy.X0))
    ocp.joint_constraint(Z, feedback=toy.K, tube=(np.array([0.0, 0.5, 1.0]), toy.X0),
                         name="joint2")


# -- 3. h_rows that raises ------------------------------------------------------------------------
def test_raising_h_rows_is_wrapped() -> None:
    x = ca.SX.sym("x", 2)
    h = ca.Function("h", [x], [ca.sumsqr(x) - 1.0])

    def broken(X: np.ndarray) -> np.ndarray:
        raise ZeroDivisionError("boom")

    with pytest.raises(BalustradeError, match="h_rows") as err:
        GridPCBFFilter(pendulum(), pendulum_setup().U, h, half_width=0.5, spacing=0.1,
                       h_rows=broken)
    assert isinstance(err.value.__cause__, ZeroDivisionError)
    with pytest.raises(BalustradeError, match="h_rows"):
        GridPCBFFilter(pendulum(), pendulum_setup().U, h, half_width=0.5, spacing=0.1,
                       h_rows=lambda X: ["a"] * len(X))


# -- 4. support_rows is row_supports ----------------------------------------------------------
def test_support_rows_equals_feedback_support(toy) -> None:
    Z = JointPolytope(toy.F, toy.G)
    D = Z.closed_loop(toy.K)
    lp = Z.feedback_support(toy.K, toy.X0)
    np.testing.assert_allclose(support_rows(toy.X0, D), lp, atol=1e-12)
    np.testing.assert_allclose(support_rows(toy.X0, D, toy.X0.vertices()),
                               Z.feedback_support(toy.K, toy.X0, toy.X0.vertices()),
                               atol=1e-12)
    np.testing.assert_allclose(support_rows(toy.X0, D, toy.X0.vertices()), lp, atol=1e-7)
    with pytest.raises(BalustradeError, match="unbounded"):      # was inf silently
        support_rows(Box([-1.0, -np.inf], [1.0, 1.0]), D)
