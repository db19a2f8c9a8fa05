"""The CasADi backend (issue #12): exact, non-degenerate norm lowering (checked against an
independent cvxpy/Clarabel model of (2.24)), statuses of IPOPT and sqpmethod on infeasible
and truncated problems, and option handling (unknown options, sqpmethod with OSQP)."""

from __future__ import annotations

import casadi as ca
import cvxpy as cp
import numpy as np
import pytest

from balustrade.backends import compile
from balustrade.backends.casadi_backend import _status, _unbounded, solver_options
from balustrade.dsl import OCP, Box, LinearSystem
from balustrade.dsl.costs import norm, squared_norm
from balustrade.errors import SolverError
from balustrade.problems.pcbf import pcbf_slack_problem

#: a grid over and around the pendulum's X = [−0.5, 0.5] × [−1.5, 1.5]
pytestmark = pytest.mark.filterwarnings("ignore:Solution may be inaccurate")

GRID = [np.array([a, b]) for a in np.linspace(-0.8, 0.8, 5) for b in np.linspace(-2.4, 2.4, 5)]


def _reference_h_pb(pend, x0: np.ndarray, ord: float) -> float:
    """(2.24) written directly in cvxpy (not through balustrade's cvxpy backend), Clarabel."""
    A, B, N = pend.system.A, pend.system.B, pend.N
    x, u = cp.Variable((2, N + 1)), cp.Variable((1, N))
    xi, xi_N = cp.Variable((4, N), nonneg=True), cp.Variable(nonneg=True)
    H, h = pend.X.H, pend.X.h
    cons = [x[:, 0] == x0, x[:, 1:] == A @ x[:, :-1] + B @ u, cp.abs(u) <= 3.0,
            H @ x[:, :N] - h[:, None] + pend.deltas[None, :] <= xi,
            cp.quad_form(x[:, N], pend.h_f.P) - 1.0 <= xi_N]
    cost = pend.alpha_f * xi_N + sum(cp.norm(xi[:, i], ord) for i in range(N))
    prob = cp.Problem(cp.Minimize(cost), cons)
    prob.solve(solver="CLARABEL", tol_gap_abs=1e-9, tol_gap_rel=1e-9, tol_feas=1e-9)
    assert prob.status in ("optimal", "optimal_inaccurate"), prob.status
    return float(prob.value)


@pytest.fixture(scope="module")
def norm2_slack(pend):
    ocp = pcbf_slack_problem(pend.system, pend.X, pend.U, pend.h_f, pend.N, pend.deltas,
                             pend.alpha_f, slack_norm=2)
    return {sv: compile(ocp, "casadi", sv) for sv in ("ipopt", "sqpmethod")}


def test_terminal_cbf_shape_for_the_reference(pend):
    """The reference model's terminal row is the CBF's own ``xᵀPx − 1`` (checked)."""
    x = np.array([0.1, -0.2])
    assert pend.h_f(x) == pytest.approx(x @ pend.h_f.P @ x - 1.0, abs=1e-12)


@pytest.mark.parametrize("solver", ["ipopt", "sqpmethod"])
def test_norm2_slack_problem_matches_clarabel_on_a_grid(pend, norm2_slack, solver):
    """(2.24) with the default 2-norm: the value of every state of a grid inside and outside
    the safe set is the conic optimum, with a success status (the old ``aᵀa <= t²`` epigraph
    got 17 (IPOPT) / 12 (sqpmethod) of 81 such states wrong by orders of magnitude)."""
    wrong = []
    for x in GRID:
        sol = norm2_slack[solver].solve({"x0": x})
        ref = _reference_h_pb(pend, x, 2)
        if not sol.success or abs(sol.objective - ref) > 1e-6 + 1e-5 * abs(ref):
            wrong.append((x.tolist(), sol.status, sol.objective, ref))
    assert not wrong, wrong


@pytest.mark.parametrize("ord", [1, np.inf])
def test_polyhedral_norms_match_clarabel(pend, ord):
    ocp = pcbf_slack_problem(pend.system, pend.X, pend.U, pend.h_f, pend.N, pend.deltas,
                             pend.alpha_f, slack_norm=ord)
    for solver in ("ipopt", "sqpmethod"):
        c = compile(ocp, "casadi", solver)
        for x in GRID[::3]:
            sol, ref = c.solve({"x0": x}), _reference_h_pb(pend, x, ord)
            assert sol.status == "optimal", (solver, x, sol.summary())
            assert sol.objective == pytest.approx(ref, rel=1e-5, abs=1e-6), (solver, x)


def test_norm_lowering_of_signed_expressions_is_exact():
    """Norms of signed expressions (no nonnegativity to exploit): ``min ‖y − c‖ + ½‖y‖²``,
    by hand for the 2-norm, by cvxpy for the 1- and ∞-norms."""
    system = LinearSystem([[1.0]], [[1.0]])
    c = ca.DM([3.0, -4.0])
    # min_y ‖y − c‖₂ + ½‖y‖², ‖c‖ = 5: stationarity y = (c − y)/‖c − y‖ gives y = c/‖c‖,
    # value (‖c‖ − 1) + ½ = 4.5
    ocp = OCP(system, 1, name="prox")
    x = ocp.variable("y", 2)
    ocp.minimize(norm(x - c, 2) + squared_norm(x) * 0.5)
    for solver in ("ipopt", "sqpmethod"):
        sol = compile(ocp, "casadi", solver).solve({})
        assert sol.status == "optimal" and sol.objective == pytest.approx(4.5, abs=1e-7)
        assert np.allclose(sol["y"].ravel(), np.array([0.6, -0.8]), atol=1e-6)
    # 1- and ∞-norms of a signed expression: value by cvxpy
    for ord in (1, np.inf):
        y = cp.Variable(2)
        ref = cp.Problem(cp.Minimize(cp.norm(y - np.array([3.0, -4.0]), ord)
                                     + 0.5 * cp.sum_squares(y))).solve()
        ocp = OCP(system, 1, name=f"prox{ord}")
        yv = ocp.variable("y", 2)
        ocp.minimize(norm(yv - c, ord) + squared_norm(yv) * 0.5)
        for solver in ("ipopt", "sqpmethod"):
            sol = compile(ocp, "casadi", solver).solve({})
            assert sol.status == "optimal" and sol.objective == pytest.approx(ref, abs=1e-6)


# -- statuses ---------------------------------------------------------------------------------
def _small_ocp(kind: str) -> OCP:
    """x0 = (3, 0) outside |x| <= 1 with hard state constraints: infeasible; LP-, QP- and
    NLP-like (2-norm) costs."""
    ocp = OCP(LinearSystem([[1.0, 0.1], [0.0, 1.0]], [[0.0], [0.1]]), 3, name=f"hard_{kind}")
    ocp.initial_state(ocp.parameter("x0", 2))
    ocp.dynamics()
    ocp.input_constraint(Box.symmetric([1.0]))
    ocp.state_constraint(Box.symmetric([1.0, 1.0]))
    cost = {"LP": norm(ocp.u, 1), "QP": squared_norm(ocp.u), "NLP": norm(ocp.x, 2)}[kind]
    ocp.minimize(cost)
    return ocp


@pytest.mark.parametrize("kind", ["LP", "QP", "NLP"])
@pytest.mark.parametrize("solver", ["ipopt", "sqpmethod"])
def test_infeasible_problems_are_reported_infeasible(kind, solver):
    c = compile(_small_ocp(kind), "casadi", solver)
    sol = c.solve({"x0": [3.0, 0.0]})
    assert sol.status == "infeasible", sol.summary()
    assert c.solve({"x0": [0.2, 0.1]}).status == "optimal"


def test_sqpmethod_alone_does_not_claim_infeasibility():
    """Without the retry chain's IPOPT there is no evidence: sqpmethod's failed line search
    stays ``failed`` (documented), never ``optimal`` or ``feasible``."""
    sol = compile(_small_ocp("LP"), "casadi", "sqpmethod", retries=[]).solve({"x0": [3, 0]})
    assert sol.status == "failed" and "Search_Direction" in sol.message


@pytest.mark.parametrize("solver,opt", [("ipopt", {"ipopt.max_iter": 1}),
                                        ("sqpmethod", {"max_iter": 1})])
def test_truncated_solves_are_not_optimal(pend, solver, opt):
    ocp = pcbf_slack_problem(pend.system, pend.X, pend.U, pend.h_f, pend.N, pend.deltas,
                             pend.alpha_f, slack_norm=2)
    sol = compile(ocp, "casadi", solver, opt, retries=[]).solve({"x0": [0.6, 1.0]})
    assert sol.status in ("max_iterations", "feasible") and "Maximum_Iterations" in sol.message


@pytest.mark.parametrize("solver", ["ipopt", "sqpmethod"])
def test_unbounded_problem_is_failed_not_feasible(solver):
    """``min v`` with ``v`` free: IPOPT's iterates diverge (objective ~ -1e20 at a
    "primal-feasible" point); this used to come back ``feasible`` (usable in a closed loop).
    sqpmethod's default retry chain ends with IPOPT, which gives the same evidence."""
    ocp = OCP(name="unbounded")
    ocp.minimize(ocp.variable("v", 1)[0])
    sol = compile(ocp, "casadi", solver).solve({})
    assert sol.status == "failed" and not sol.usable, sol.summary()
    assert "appears unbounded" in sol.message and "Diverging_Iterates" in sol.message
    bounded = OCP(name="bounded")
    bounded.minimize(bounded.variable("v", 1, lb=-2.0)[0])
    assert compile(bounded, "casadi", solver).solve({}).objective == pytest.approx(-2.0)


def test_unbounded_evidence():
    assert _unbounded("Diverging_Iterates", -1.0) == "diverging iterates"
    assert "objective" in _unbounded("Maximum_Iterations_Exceeded", -7e21)
    assert "objective" in _unbounded("Solve_Succeeded", -np.inf)
    assert _unbounded("Maximum_Iterations_Exceeded", -1e9) is None
    assert _unbounded("Restoration_Failed", np.nan) is None


def test_return_status_mapping():
    assert _status({"success": True, "return_status": "Solve_Succeeded"}) == "optimal"
    # CasADi flags IPOPT's acceptable level as success; it is not a certified optimum
    assert _status({"success": True, "return_status": "Solved_To_Acceptable_Level"}) \
        == "optimal_inaccurate"
    assert _status({"success": False, "return_status": "Infeasible_Problem_Detected"}) \
        == "infeasible"
    assert _status({"success": False, "return_status": "Maximum_Iterations_Exceeded"}) \
        == "max_iterations"
    for msg in ("Restoration_Failed", "Search_Direction_Becomes_Too_Small",
                "Invalid_Number_Detected"):
        assert _status({"success": False, "return_status": msg}) == "failed"


# -- options ----------------------------------------------------------------------------------
@pytest.mark.parametrize("solver,options,names", [
    ("ipopt", {"bogus": 1}, ["'bogus'", "'ipopt'"]),
    ("ipopt", {"ipopt.bogus": 1}, ["ipopt.bogus", "IPOPT"]),
    ("sqpmethod", {"max_iters": 3}, ["'max_iters'", "'sqpmethod'", "max_iter"]),
    ("sqpmethod", {"qpsol_options": {"nonsense": 1}}, ["'nonsense'", "'qrqp'"]),
    ("sqpmethod", {"qpsol": "osqp", "qpsol_options": {"print_header": False}},
     ["'print_header'", "'osqp'"]),
])
def test_unknown_options_raise_solver_error_naming_option_and_solver(pend, solver, options,
                                                                     names):
    with pytest.raises(SolverError) as err:
        compile(pend.slack, "casadi", solver, options)
    for name in names:
        assert name in str(err.value), str(err.value)


def test_qpsol_defaults_follow_the_chosen_qp_solver():
    assert "print_header" in solver_options("sqpmethod")["qpsol_options"]
    osqp = solver_options("sqpmethod", {"qpsol": "osqp",
                                        "qpsol_options": {"osqp": {"verbose": True}}})
    assert "print_header" not in osqp["qpsol_options"]
    assert osqp["qpsol_options"]["osqp"]["verbose"] is True            # user's value wins
    assert osqp["qpsol_options"]["osqp"]["eps_abs"] == 1e-9            # default kept


@pytest.mark.parametrize("slack_norm", [1, pytest.param(2, marks=pytest.mark.slow)])
def test_sqpmethod_with_osqp_agrees_with_the_default(pend, slack_norm):
    """The documented ``{"qpsol": "osqp"}`` path builds and solves the pendulum (2.24) to the
    default's value (2-norm: sqpmethod + OSQP needs more than 100 iterations; the retry chain
    finishes and says so)."""
    ocp = pcbf_slack_problem(pend.system, pend.X, pend.U, pend.h_f, pend.N, pend.deltas,
                             pend.alpha_f, slack_norm=slack_norm)
    osqp = compile(ocp, "casadi", "sqpmethod", {"qpsol": "osqp"})
    default = compile(ocp, "casadi", "sqpmethod")
    for x in ([0.49, 0.5], [-0.6, 0.0], [0.3, -1.0]):
        a, b = osqp.solve({"x0": x}), default.solve({"x0": x})
        assert a.success and b.status == "optimal", (a.summary(), b.summary())
        assert a.objective == pytest.approx(b.objective, rel=1e-6, abs=1e-7)
