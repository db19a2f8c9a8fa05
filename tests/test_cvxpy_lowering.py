"""The cvxpy lowering gives no wrong answers (issue #12): quadratic rows about their centre
(the tube row (5.15b) at |x_k| ≈ 100), large numbers (weights, "unbounded" bounds) and the
status of every outcome, each against an independent computation (CasADi/IPOPT on the same
OCP, or by hand)."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from balustrade.backends import compile
from balustrade.backends import cvxpy_backend as cb
from balustrade.backends.passes.classify import joint_quadratic
from balustrade.dsl.ocp import OCP

# the first 12 states of the disturbed Algorithm 5.2 closed loop of benchmarks/bench_robust.py
# (rendezvous, N = 200, CasADi, seed 0), rounded to 6 digits; the first four (|x| >= 31) made
# Clarabel fail when the tube row was expanded around zero
RENDEZVOUS_STATES = np.array([
    [100.0, 100.0, 100.0, 0.0, 0.0, 0.0],
    [90.303366, 90.403124, 90.34069, -19.320554, -19.359106, -19.777486],
    [61.335146, 61.88086, 61.146199, -39.161679, -37.307626, -38.198252],
    [30.244595, 30.996733, 30.396701, -22.871698, -24.285075, -23.256607],
    [9.456699, 9.51814, 9.425088, -18.251398, -18.370209, -19.183531],
    [0.35633, 0.427482, -1.527123, 0.46927, -0.338733, -2.491053],
    [0.566497, 0.267191, -2.863096, -0.372075, 0.383053, -0.139408],
    [0.405155, 0.411563, -2.821895, -0.152501, -0.17302, -0.249871],
    [0.377024, 0.329411, -2.831025, -0.278876, 0.178509, 0.3788],
    [0.324113, 0.386764, -2.650232, 0.287624, -0.181631, 0.479993],
    [0.460848, 0.311942, -2.516941, 0.467404, 0.218533, -0.062954],
    [0.592875, 0.386958, -2.601388, -0.015846, -0.177341, -0.470842],
])


def _rendezvous_slack(N: int):
    from balustrade.problems.robust import robust_pcbf_slack_problem
    from balustrade.reproduce.rendezvous import design

    d = design(N, 40)
    s = d["setup"]
    return robust_pcbf_slack_problem(d["system"], s.X, s.U, d["cbf"], N, s.deltas(),
                                     d["error"], s.alpha_f)


def _check_rendezvous(N: int) -> None:
    ocp = _rendezvous_slack(N)
    cv = compile(ocp, "cvxpy")
    ip = compile(ocp, "casadi", "ipopt", {"ipopt.mu_strategy": "adaptive"})
    assert cv.solver_name == "CLARABEL"
    for x in RENDEZVOUS_STATES:
        a, b = cv.solve({"x0": x}), ip.solve({"x0": x})
        assert b.success, b.summary()
        assert a.success, (x, a.summary())
        assert a.objective == pytest.approx(b.objective, rel=1e-6, abs=1e-6), x


def test_rendezvous_benchmark_states_solve_on_cvxpy():
    """(5.15) of the rendezvous at the benchmark states (N = 30: the same four states
    failed there): cvxpy/Clarabel matches CasADi/IPOPT at every state."""
    _check_rendezvous(30)


@pytest.mark.slow
def test_rendezvous_benchmark_states_solve_on_cvxpy_n200():
    _check_rendezvous(200)


def test_joint_quadratic_keeps_the_ellipsoid_about_its_centre():
    """(x − z − c)ᵀP(x − z − c) − 1 with x a parameter, z a variable: ½‖L_w z + L_p x + l‖²
    − 1 with L_p = −L_w, no affine part, the centre in l; equal to the row everywhere."""
    rng = np.random.default_rng(0)
    R = rng.normal(size=(3, 3))
    P, centre = R @ R.T + np.eye(3), rng.normal(size=3)
    z, x = ca.SX.sym("z", 3), ca.SX.sym("x", 3)
    d = x - z - centre
    row = ca.mtimes([d.T, ca.DM(P), d]) - 1
    jq = joint_quadratic(row, z, x)
    assert jq is not None and jq.linear_free
    assert jq.c == pytest.approx(-1.0, abs=1e-12)
    np.testing.assert_allclose(jq.Lw, -jq.Lp, atol=1e-12)
    np.testing.assert_allclose(jq.Lw.T @ jq.Lw, 2 * P, rtol=1e-12)  # Hessian in z
    f = ca.Function("f", [z, x], [row])
    for _ in range(5):
        zv, xv = rng.normal(size=3) * 100, rng.normal(size=3) * 100
        v = jq.Lw @ zv[jq.w_index] + jq.Lp @ xv[jq.p_index] + jq.l
        assert 0.5 * v @ v + jq.c == pytest.approx(float(f(zv, xv)), rel=1e-12)
    # an indefinite joint Hessian (−xᵀPx) or a non-quadratic parameter part: not this form
    assert joint_quadratic(z.T @ z - x.T @ x, z, x) is None
    assert joint_quadratic(z.T @ z - ca.cos(x[0]), z, x) is None


def test_tube_row_far_from_origin_is_exact():
    """min ‖z‖² s.t. (x − z)ᵀP(x − z) <= 1 at |x| = 1e3: the answer is the ellipsoid's point
    nearest 0, computed by hand (P = I: z = x (1 − 1/|x|))."""
    ocp = OCP(name="far_tube")
    z = ocp.variable("z", 3)
    x = ocp.parameter("x", 3)
    ocp.le((x - z).T @ (x - z), 1.0)
    ocp.minimize(z.T @ z)
    compiled = compile(ocp, "cvxpy")
    for xv in (np.array([1e3, -2e3, 5e2]), np.array([3.0, 0.0, 0.0])):
        sol = compiled.solve({"x": xv})
        assert sol.status == "optimal", sol.summary()
        expected = xv * (1 - 1 / np.linalg.norm(xv))
        np.testing.assert_allclose(sol["z"].ravel(), expected, rtol=1e-7, atol=1e-7)


# -- large numbers and statuses ---------------------------------------------------------------

def _named(name: str) -> tuple[OCP, dict | None]:
    ocp = OCP(name=name)
    params = None
    if name == "huge_weight_quadratic":  # min 1e12 u0² + u1², u0 + u1 >= 1: u1 ≈ 1, cost ≈ 1
        u = ocp.variable("u", 2)
        ocp.le(1.0 - u[0] - u[1], 0)
        ocp.minimize(1e12 * u[0] ** 2 + u[1] ** 2)
    elif name == "huge_weight_soft":  # exact penalty, feasible: ξ = 1, u = (1, 1)
        u = ocp.variable("u", 2, lb=-1.0, ub=1.0)
        xi = ocp.variable("xi", 1, lb=0.0)
        ocp.le(3.0 - u[0] - u[1], xi)
        ocp.minimize(1e12 * xi[0] + u[0] ** 2 + u[1] ** 2)
    elif name == "big_bounds":  # |u| <= 1e12 meaning "unbounded": projection, cost 0.5
        u = ocp.variable("u", 2, lb=-1e12, ub=1e12)
        x0 = ocp.parameter("x0", 2)
        ocp.le(u[0] + u[1] - 1.0, 0)
        ocp.minimize((u[0] - x0[0]) ** 2 + (u[1] - x0[1]) ** 2)
        params = {"x0": np.array([3.0, -1.0])}
    elif name == "infinite_bounds":  # 1e30 bounds and a 1e25 row: cost 0.5
        u = ocp.variable("u", 2, lb=-1e30, ub=1e30)
        ocp.le(u[0] + u[1] - 1.0, 0)
        ocp.le(u[0] - 1e25, 0)
        ocp.minimize((u[0] - 3) ** 2 + (u[1] + 1) ** 2)
    elif name == "active_big_bound":  # min u0 + u1/2, u0 <= u1, u >= -1e12: u = (-1e12, -1e12)
        u = ocp.variable("u", 2, lb=-1e12, ub=1e12)
        ocp.le(u[0] - u[1], 0)
        ocp.minimize(u[0] + 0.5 * u[1])
    elif name == "infeasible":
        u = ocp.variable("u", 1, lb=0.0)
        ocp.le(u + 1.0, 0)
        ocp.minimize(u[0] ** 2)
    elif name == "unbounded":
        u = ocp.variable("u", 2)
        ocp.le(u[0] - u[1], 0)
        ocp.minimize(u[0] + u[1])
    return ocp, params


@pytest.mark.parametrize("solver", ["PIQP", "CLARABEL"])
@pytest.mark.parametrize("name,objective", [("huge_weight_quadratic", 1.0),
                                            ("huge_weight_soft", 1e12 + 2.0),
                                            ("big_bounds", 0.5), ("infinite_bounds", 0.5)])
def test_feasible_problems_with_large_numbers_are_solved(name, objective, solver):
    ocp, params = _named(name)
    sol = compile(ocp, "cvxpy", solver).solve(params)
    assert sol.success, sol.summary()
    assert sol.objective == pytest.approx(objective, rel=1e-9), sol.summary()
    ref = compile(ocp, "casadi", "ipopt").solve(params)
    assert ref.objective == pytest.approx(objective, rel=1e-6)


def test_active_large_bound_is_imposed():
    """A 1e12 bound left out of the first solve is imposed when the relaxation violates it
    (here the relaxation is unbounded)."""
    ocp, _ = _named("active_big_bound")
    for solver in ("PIQP", "CLARABEL"):
        sol = compile(ocp, "cvxpy", solver).solve()
        if solver == "PIQP":
            assert sol.success, sol.summary()
            np.testing.assert_allclose(sol["u"].ravel(), [-1e12, -1e12], rtol=1e-9)
        else:  # Clarabel cannot solve it, and says so
            assert sol.success or sol.status == "failed", sol.summary()
        assert "large bounds" in sol.message


@pytest.mark.parametrize("solver", ["PIQP", "CLARABEL"])
def test_statuses_say_what_happened(solver):
    ocp, _ = _named("infeasible")
    sol = compile(ocp, "cvxpy", solver).solve()
    assert sol.status == "infeasible", sol.summary()
    ocp, _ = _named("unbounded")
    sol = compile(ocp, "cvxpy", solver).solve()
    assert sol.status == "failed" and "unbounded" in sol.message, sol.summary()
    ocp, _ = _named("huge_weight_quadratic")
    sol = compile(ocp, "cvxpy", solver, {"max_iter": 1}).solve()
    assert sol.status == "max_iterations", sol.summary()
    words = {"PIQP": "PIQP_MAX_ITER_REACHED", "CLARABEL": "MaxIterations"}[solver]
    assert words in sol.message and np.all(np.isnan(sol.w))


def test_a_numerical_infeasibility_verdict_is_not_reported():
    """PIQP calls min 1e12 ξ² + u0², u + ξ >= x0, |u| <= 1 'primal infeasible' at
    x0 = (10, −5), a feasible problem: never report that as 'infeasible'."""
    ocp = OCP(name="huge_quadratic_penalty")
    u = ocp.variable("u", 2, lb=-1.0, ub=1.0)
    xi = ocp.variable("xi", 2, lb=0.0)
    x0 = ocp.parameter("x0", 2)
    ocp.le(x0 - u - xi, 0)
    ocp.minimize(1e12 * (xi[0] ** 2 + xi[1] ** 2) + u[0] ** 2)
    for solver in ("PIQP", "CLARABEL"):
        compiled = compile(ocp, "cvxpy", solver)
        for x in (np.array([10.0, -5.0]), np.array([3.0, 2.0]), np.array([1e3, 1.0])):
            sol = compiled.solve({"x0": x})
            assert sol.status != "infeasible", sol.summary()
            if sol.success:  # u = 1 where x0 >= 1, ξ = max(x0 − 1, 0): 1e12 Σ ξ² + 1
                xi_ref = np.maximum(x - 1, 0)
                assert sol.objective == pytest.approx(1e12 * xi_ref @ xi_ref + 1, rel=1e-6)


def _feasible_cone() -> OCP:
    """Feasible with a second-order cone: min ‖u − 3‖₂ s.t. u0 + u1 <= 1, |u| <= 5."""
    from balustrade.dsl.costs import norm

    ocp = OCP(name="cone_feasible")
    u = ocp.variable("u", 2, lb=-5.0, ub=5.0)
    ocp.le(u[0] + u[1] - 1.0, 0, name="sum")
    ocp.minimize(norm(u - 3.0, 2))
    return ocp


def _always_infeasible(problem, solver, options, warm_start):
    """A solver that answers "infeasible" to everything it is asked, re-checks included."""
    return cb.Status.INFEASIBLE, "infeasible (patched: always infeasible)"


@pytest.mark.parametrize(("solver", "name"), [("PIQP", "huge_weight_quadratic"),
                                              ("CLARABEL", "huge_weight_quadratic"),
                                              ("CLARABEL", "cone"),   # PIQP takes no cones
                                              ("CLARABEL", "big_bounds")])  # the full re-solve
def test_a_solver_always_saying_infeasible_is_caught(monkeypatch, solver, name):
    """The verdict needs evidence beyond the solver's word: the old re-check asked the same
    solver again, which repeated it, and reported ``infeasible`` for a feasible problem; the
    independent check (the direct lowering's feasibility solve) finds a feasible point, so
    the status is ``failed`` with the reason."""
    ocp, params = (_feasible_cone(), None) if name == "cone" else _named(name)
    compiled = compile(ocp, "cvxpy", solver)
    monkeypatch.setattr(cb, "_run", _always_infeasible)
    sol = compiled.solve(params)
    assert sol.status == "failed", sol.summary()
    assert "patched" in sol.message, sol.message
    assert ("constraints alone are feasible" in sol.message      # a point found, or (the
            or "infeasibility not established" in sol.message), sol.message  # 1e12 bounds)
    assert np.all(np.isnan(sol.w)) and np.isnan(sol.objective)


@pytest.mark.parametrize("solver", ["PIQP", "CLARABEL"])
def test_a_real_infeasibility_is_confirmed_independently(solver):
    """A truly infeasible problem stays ``infeasible``, and the message says what confirmed
    it (a checked certificate or the other engine on the constraints alone)."""
    sol = compile(_named("infeasible")[0], "cvxpy", solver).solve()
    assert sol.status == "infeasible", sol.summary()
    assert "certificate" in sol.message or "confirmed by" in sol.message, sol.message


def test_without_an_independent_check_infeasible_becomes_failed(monkeypatch):
    """An OCP the direct chain cannot lower has no independent check: ``failed``, saying
    why, never an unconfirmed ``infeasible``."""
    from balustrade.backends import direct_backend
    from balustrade.errors import ConvexityError

    def refuse(self, *args, **kwargs):
        raise ConvexityError("refused for the test")

    monkeypatch.setattr(direct_backend.DirectCompiled, "__init__", refuse)
    sol = compile(_named("infeasible")[0], "cvxpy", "CLARABEL").solve()
    assert sol.status == "failed", sol.summary()
    assert "infeasibility not established" in sol.message and "refused for the test" in \
        sol.message, sol.message


def test_solver_options_are_valid_settings():
    """Every default option of PIQP and Clarabel names a real setting of the solver."""
    import clarabel
    import piqp

    piqp_settings = set(dir(piqp.SparseSolver().settings))
    clarabel_settings = set(dir(clarabel.DefaultSettings()))
    assert set(cb.SOLVER_OPTIONS["PIQP"]) <= piqp_settings
    assert set(cb.SOLVER_OPTIONS["CLARABEL"]) <= clarabel_settings
