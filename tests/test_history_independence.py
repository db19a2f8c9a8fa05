"""A solve without a warm start depends on its parameters only (issue #12): the same
parameters give the same answer on a fresh compile and after 100 other solves, on every
backend (cvxpy with PIQP and Clarabel, CasADi with IPOPT and sqpmethod). The history
mixes feasible, infeasible and far-away states, which used to leave Clarabel's and PIQP's
solver objects (and their equilibration of the previous data) behind in cvxpy's cache."""

from __future__ import annotations

import numpy as np
import pytest

from balustrade.backends import compile
from balustrade.dsl.ocp import OCP
from balustrade.dsl.sets import Box
from balustrade.dsl.system import LinearSystem

N = 10


def _double_integrator_mpc() -> OCP:
    """A QP: nominal MPC of a double integrator, hard state/input boxes, initial state
    ``x0`` a parameter (infeasible for far states)."""
    system = LinearSystem(np.array([[1.0, 0.1], [0.0, 1.0]]), np.array([[0.005], [0.1]]))
    ocp = OCP(system, N, name="di_mpc")
    x0 = ocp.parameter("x0", 2)
    ocp.initial_state(x0)
    ocp.dynamics()
    ocp.state_constraint(Box([-5.0, -2.0], [5.0, 2.0]), steps=range(1, N + 1))
    ocp.input_constraint(Box([-1.0], [1.0]))
    ocp.minimize(sum(ocp.x[0, i] ** 2 + 0.1 * ocp.x[1, i] ** 2 for i in range(N + 1))
                 + sum(0.1 * ocp.u[0, i] ** 2 for i in range(N)))
    return ocp


def _history(rng: np.random.Generator, scale: np.ndarray, n: int = 100) -> np.ndarray:
    """Mostly inside, some 3x outside, a few at 100x: every status the solver can give."""
    factors = rng.choice([1.0, 3.0, 100.0], size=(n, 1), p=[0.6, 0.3, 0.1])
    return rng.uniform(-1.0, 1.0, size=(n, scale.size)) * scale * factors


def _same_after_history(compiled, x_star: np.ndarray, history: np.ndarray) -> None:
    fresh = compiled.solve({"x0": x_star})
    for x in history:
        compiled.solve({"x0": x})
    again = compiled.solve({"x0": x_star})
    assert again.status == fresh.status, (fresh.summary(), again.summary())
    assert fresh.success, fresh.summary()
    _assert_same(again.w, fresh.w, "after 100 other solves")
    # and a freshly compiled problem agrees too (nothing was cached at compile time)
    other = compile(compiled.ocp, compiled.backend, compiled.solver_name,
                    getattr(compiled, "solver_options", None)
                    if compiled.backend == "cvxpy" else None).solve({"x0": x_star})
    _assert_same(other.w, fresh.w, "on a fresh compile")


def _assert_same(w: np.ndarray, w_ref: np.ndarray, when: str) -> None:
    gap = np.abs(w - w_ref) / (1.0 + np.abs(w_ref))
    assert np.all(gap <= 1e-12), f"{when}: the solution moved by {gap.max():.3g} (relative)"


@pytest.fixture(scope="module")
def di_mpc() -> OCP:
    return _double_integrator_mpc()


@pytest.mark.parametrize("backend,solver", [("cvxpy", "PIQP"), ("cvxpy", "CLARABEL"),
                                            ("casadi", "ipopt"), ("casadi", "sqpmethod")])
def test_qp_answer_does_not_depend_on_history(di_mpc, backend, solver):
    compiled = compile(di_mpc, backend, solver)
    rng = np.random.default_rng(3)
    _same_after_history(compiled, np.array([3.0, -1.0]), _history(rng, np.array([5.0, 2.0])))


@pytest.mark.parametrize("backend,solver", [("cvxpy", "CLARABEL"), ("casadi", "ipopt"),
                                            ("casadi", "sqpmethod")])
def test_tube_problem_answer_does_not_depend_on_history(unstable2d_tube, backend, solver):
    """(5.15) with its second-order-cone tube row: Clarabel after a closed-loop-like history."""
    compiled = compile(unstable2d_tube["slack"], backend, solver)
    rng = np.random.default_rng(4)
    _same_after_history(compiled, np.array([1.2, -2.0]),
                        _history(rng, np.array([1.3, 2.5])))


def test_warm_start_is_accepted_and_harmless(di_mpc):
    """A warm start (previous Solution or dict) is accepted on every cvxpy solver; for
    PIQP/Clarabel (no warm start through cvxpy) it changes nothing."""
    for solver in ("PIQP", "CLARABEL", "OSQP"):
        compiled = compile(di_mpc, "cvxpy", solver)
        x = np.array([1.0, 0.5])
        cold = compiled.solve({"x0": x})
        warm = compiled.solve({"x0": x + 0.01}, warm_start=cold)
        also = compiled.solve({"x0": x + 0.01}, warm_start={"x": cold["x"], "u": cold["u"]})
        fresh = compiled.solve({"x0": x + 0.01})
        assert cold.success and warm.success and also.success and fresh.success
        assert warm.objective == pytest.approx(fresh.objective, rel=1e-6, abs=1e-8)
        if solver != "OSQP":
            np.testing.assert_array_equal(warm.w, fresh.w)
            np.testing.assert_array_equal(also.w, fresh.w)
