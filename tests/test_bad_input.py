"""Bad input gets a balustrade exception that names the block and the shapes."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from balustrade.backends import compile
from balustrade.dsl import OCP, Box, Ellipsoid, FunctionSet, LinearSystem, Polytope, quad
from balustrade.errors import (
    BalustradeError,
    ConvexityError,
    EmptySetError,
    NonFiniteError,
    NotPSDError,
    ShapeError,
    SolverError,
)
from balustrade.problems.mpc import mpc_problem


def test_wrong_system_shapes():
    square = r"A: expected a square matrix \(nx, nx\), got shape \(2, 3\)"
    with pytest.raises(ShapeError, match=square):
        LinearSystem(np.ones((2, 3)), np.ones((2, 1)))
    with pytest.raises(ShapeError, match=r"B: expected shape \(3, n\), got shape \(2, 1\)"):
        LinearSystem(np.eye(3), np.ones((2, 1)))
    with pytest.raises(ShapeError, match=r"f\(x, u, w, theta\)"):
        from balustrade.dsl import System

        System(lambda x, u: x[0] + u, nx=2, nu=1, name="pendulum")


def test_wrong_set_shapes_and_empty_sets():
    with pytest.raises(ShapeError, match="h must have one entry per row of H"):
        Polytope(np.eye(2), np.ones(3), name="X")
    with pytest.raises(ShapeError, match=r"U: ub: expected shape \(2,\), got shape \(3,\)"):
        Box(np.zeros(2), np.ones(3), name="U")
    with pytest.raises(EmptySetError, match="X"):
        Polytope(np.array([[1.0], [-1.0]]), np.array([-1.0, 0.0]), name="X")
    with pytest.raises(EmptySetError, match="lower bound exceeds upper bound"):
        Box([1.0], [0.0])
    with pytest.raises(EmptySetError, match="tightening X by E leaves an empty set"):
        Box.symmetric([0.1, 0.1], name="X").tighten(Ellipsoid(np.eye(2), name="E"))


def test_set_of_wrong_dimension_in_ocp(pend):
    ocp = OCP(pend.system, 3)
    with pytest.raises(ShapeError, match=r"state: set U: expected dimension 2, got dimension 1"):
        ocp.state_constraint(pend.U)


def test_nan_and_wrong_shape_parameters(pend):
    c = pend.compiled["slack", "casadi"]
    with pytest.raises(NonFiniteError, match="parameter 'x0'"):
        c.solve({"x0": [np.nan, 0.0]})
    wrong = r"parameter .x0.: expected shape \(2, 1\), got shape \(3,\)"
    with pytest.raises(ShapeError, match=wrong):
        c.solve({"x0": [0.0, 0.0, 0.0]})
    with pytest.raises(BalustradeError, match="no value for parameter 'x0'"):
        c.solve({})
    with pytest.raises(NonFiniteError, match=r"pendulum.step: x"):
        pend.system.step([np.inf, 0.0], [0.0])


def test_non_psd_weights(pend):
    with pytest.raises(NotPSDError, match="Q"):
        quad(ca.SX.sym("x", 2), -np.eye(2), label="stage")
    with pytest.raises(NotPSDError, match="Q"):
        mpc_problem(pend.system, pend.X, pend.U, None, 3, np.diag([1.0, -1.0]), np.eye(1),
                    np.eye(2))
    with pytest.raises(NotPSDError, match=r"E: P: matrix of shape \(2, 2\)"):
        Ellipsoid(np.array([[1.0, 2.0], [2.0, 1.0]]), name="E")


def test_nonconvex_function_set_refused_by_cvxpy(pend):
    ring = FunctionSet(lambda x: 0.25 - ca.sumsqr(x), dim=2, name="outside_disc")
    ocp = OCP(pend.system, 3, name="avoid")
    ocp.initial_state(ocp.parameter("x0", 2))
    ocp.dynamics()
    ocp.state_constraint(ring, name="avoid_disc")
    ocp.minimize(quad(ocp.u))
    with pytest.raises(ConvexityError, match=r"block 'avoid_disc', row \d+: .*negative eigen"):
        compile(ocp, "cvxpy")
    sol = compile(ocp, "casadi").solve({"x0": [1.0, 0.0]})  # CasADi holds it
    assert sol.success


def test_unknown_solver_names(pend):
    with pytest.raises(SolverError, match="unknown CasADi NLP solver 'snopt7'"):
        compile(pend.slack, "casadi", "snopt7")
    with pytest.raises(SolverError, match="unknown or uninstalled cvxpy solver 'GUROBI9'"):
        compile(pend.slack, "cvxpy", "GUROBI9")
    with pytest.raises(SolverError, match="unknown backend 'julia'"):
        compile(pend.slack, "julia")


@settings(max_examples=40, deadline=None)
@given(rows=st.integers(1, 4), cols=st.integers(1, 4), m=st.integers(1, 3),
       b_rows=st.integers(1, 4))
def test_linear_system_shapes_property(rows, cols, m, b_rows):
    """Any shape combination either builds a consistent system or raises ShapeError."""
    A, B = np.ones((rows, cols)), np.ones((b_rows, m))
    if rows == cols and b_rows == rows:
        sys_ = LinearSystem(A, B)
        assert sys_.nx == rows and sys_.nu == m
        assert sys_.step(np.zeros(rows), np.zeros(m)).shape == (rows,)
    else:
        with pytest.raises(ShapeError):
            LinearSystem(A, B)


@settings(max_examples=30, deadline=None)
@given(value=st.lists(st.floats(allow_nan=True, allow_infinity=True, width=64), min_size=0,
                      max_size=4))
def test_parameter_values_property(pend, value):
    """A parameter value is accepted iff it has 2 finite entries; otherwise a clear error."""
    arr = np.array(value, dtype=float)
    c = pend.compiled["slack", "cvxpy"]
    if arr.size == 2 and np.all(np.isfinite(arr)) and np.max(np.abs(arr)) < 1e3:
        assert c.solve({"x0": arr}).status in ("optimal", "optimal_inaccurate")
    elif arr.size != 2:
        with pytest.raises(ShapeError, match="parameter 'x0'"):
            c.solve({"x0": arr})
    elif not np.all(np.isfinite(arr)):
        with pytest.raises(NonFiniteError, match="parameter 'x0'"):
            c.solve({"x0": arr})


def test_solution_primal_is_the_one_source_of_truth(pend):
    """``w`` is derived from ``primal``: edits (in place or by assignment) are what verify
    checks, assigning ``w`` writes ``primal``, and a disagreeing ``w`` is refused."""
    from balustrade.backends import Solution
    from balustrade.testing import verify

    sol = pend.compiled["slack", "cvxpy"].solve({"x0": [0.1, 0.0]})
    assert verify(pend.slack, sol).ok
    sol.primal["u"][0] = 100.0                      # in place
    assert not verify(pend.slack, sol).ok
    sol.primal["u"] = np.zeros_like(sol.primal["u"]) + 100.0  # by assignment
    assert not verify(pend.slack, sol).ok
    w = sol.w.copy()
    w[:] = 0.0
    sol.w = w
    assert np.all(sol.primal["x"] == 0.0) and sol.primal["x"].shape == (2, pend.N + 1)
    given = Solution("optimal", 0.0, {"a": np.zeros(2)}, {}, 0.0, 0, "hand", "hand",
                     w=np.ones(2), p=np.zeros(0))
    assert np.all(given.primal["a"] == 1.0)         # a constructor's w is the point
    with pytest.raises(ShapeError, match=r"Solution.w: expected shape \(2,\), got shape \(3,\)"):
        Solution("optimal", 0.0, {"a": np.zeros(2)}, {}, 0.0, 0, "hand", "hand",
                 w=np.ones(3), p=np.zeros(0))
    with pytest.raises(BalustradeError, match=r"no variable named 'xi_typo'.*'xi_N'"):
        sol["xi_typo"]


def test_headline_bad_inputs_of_issue_12(pend):
    """math.sin dynamics, NaN tightening, negative alpha_f: refused, naming the thing."""
    import math

    from balustrade.dsl import System
    from balustrade.problems.pcbf import pcbf_slack_problem

    with pytest.raises(NonFiniteError, match=r"pendulum: f\(x, u, w, theta\).*ca\.sin"):
        System(lambda x, u: ca.vertcat(x[1], -math.sin(x[0]) + u), 2, 1, name="pendulum")
    args = (pend.system, pend.X, pend.U, pend.h_f, pend.N)
    nan_deltas = np.array(pend.deltas, dtype=float)
    nan_deltas[1] = np.nan
    with pytest.raises(NonFiniteError, match="pcbf_slack: tightenings deltas"):
        pcbf_slack_problem(*args, nan_deltas)
    with pytest.raises(BalustradeError, match=r"pcbf_slack: alpha_f: must lie in \(0, inf\)"):
        pcbf_slack_problem(*args, pend.deltas, alpha_f=-1.0)


def _grouped_qp_for_bad_input() -> OCP:
    """A small QP with one group of inequality rows (``ocp.row_groups``)."""
    ocp = OCP(name="grouped")
    y = ocp.variable("y", 2)
    c = ocp.parameter("c", 2)
    ocp.le(ca.mtimes(ca.DM(np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])), y), 1.0,
           name="halfspaces")
    ocp.minimize(ca.sumsqr(y - c))
    ocp.row_groups = {"halfspaces": np.zeros(3, dtype=int)}
    return ocp


@pytest.mark.parametrize("setting, named", [
    ({"per_rnd": 2}, "per_rnd"),                       # a misspelt key
    ({"stride": 2}, "stride"),                         # from ocp.row_group_stride
    ({"options": {}}, "options"),                      # from the target
    ({"max_rounds": 2.5}, "max_rounds"),
    ({"max_rounds": 0}, "max_rounds"),
    ({"drop_after": "3"}, "drop_after"),
    ({"drop_after": True}, "drop_after"),
    ({"per_round": 1.0}, "per_round"),
    ({"seed": "nearest"}, "seed"),
    ({"reduced_options": 3}, "reduced_options"),
    ("yes", "row_generation"),
])
def test_bad_row_generation_option(setting, named):
    """The option ``row_generation`` of the direct backend is checked at compile time (no
    TypeError from a keyword, no silent misuse), naming the key."""
    from balustrade.backends.direct_backend import DirectCompiled

    with pytest.raises(BalustradeError, match=named):
        DirectCompiled(_grouped_qp_for_bad_input(), "piqp", {"row_generation": setting})


def test_row_generation_empty_dict_is_on_false_is_off():
    from balustrade.backends.direct_backend import DirectCompiled

    ocp = _grouped_qp_for_bad_input()
    assert DirectCompiled(ocp, "piqp", {"row_generation": {}}).rowgen is not None
    assert DirectCompiled(ocp, "piqp", {"row_generation": False}).rowgen is None


@pytest.mark.parametrize("groups, named", [
    ({"halfspaces": np.zeros(2, dtype=int)}, r"row_groups\['halfspaces'\].*\(3,\).*\(2,\)"),
    ({"halfspaces": np.zeros(3)}, r"row_groups\['halfspaces'\].*integer"),
    ({"no_block": np.zeros(3, dtype=int)}, "no_block"),
])
def test_bad_row_groups(groups, named):
    """``ocp.row_groups`` of the wrong length (an IndexError before), of floats or naming no
    block: a SolverError naming the block, before any solve."""
    from balustrade.backends.direct_backend import DirectCompiled

    ocp = _grouped_qp_for_bad_input()
    ocp.row_groups = groups
    with pytest.raises(SolverError, match=named):
        DirectCompiled(ocp, "piqp", {"row_generation": True})


def test_bad_row_generation_value_refused_without_groups():
    """A bad value is refused even where row generation would not run (no ``row_groups``,
    or Clarabel): it is not silently ignored."""
    from balustrade.backends.direct_backend import DirectCompiled

    ocp = _grouped_qp_for_bad_input()
    del ocp.row_groups
    with pytest.raises(SolverError, match="max_rounds"):
        DirectCompiled(ocp, "piqp", {"row_generation": {"max_rounds": "many"}})
    with pytest.raises(SolverError, match="drop_after"):
        DirectCompiled(_grouped_qp_for_bad_input(), "clarabel",
                       {"row_generation": {"drop_after": 0}})
