"""The direct conic backend (issue #14 §1): the OCP lowered once to Clarabel/PIQP's own
interfaces agrees with cvxpy and CasADi, keeps the statuses honest and is history
independent."""

from __future__ import annotations

import numpy as np
import pytest

from balustrade.backends import PRESETS, DirectCompiled, compile, resolve_target
from balustrade.backends.passes.classify import Classify
from balustrade.backends.passes.to_conic import ToConic
from balustrade.dsl.costs import max_of, norm
from balustrade.dsl.ocp import OCP
from balustrade.errors import BalustradeError, ConvexityError, SolverError
from balustrade.problems.pcbf import pcbf_filter_problem, pcbf_slack_problem
from balustrade.testing import verify

STATES = np.array([[0.9, 0.0], [-0.5, 2.5], [0.3, -2.9], [0.05, 0.1], [-0.95, -1.0]])


def close(a: float, b: float, rel: float = 1e-6, abs_: float = 1e-6) -> bool:
    return abs(a - b) <= abs_ or abs(a - b) <= rel * max(abs(a), abs(b))


# -- the PCBF pair (2.24)/(2.23) of a linear system (the linearized pendulum) -------------

@pytest.fixture(scope="module")
def pair(pend):
    """(2.24) for slack norms 1, 2, ∞ and (2.23), each compiled on the three backends."""
    s = pend.setup
    args = (pend.system, s.X, s.U, pend.h_f, s.N, s.deltas)
    out = {}
    for slack_norm in (1, 2, np.inf):
        ocp = pcbf_slack_problem(*args, alpha_f=s.alpha_f, slack_norm=slack_norm)
        out[slack_norm] = (ocp, {t: compile(ocp, t) for t in ("fast-convex", "cvxpy", "exact")})
    filt = pcbf_filter_problem(*args)
    out["filter"] = (filt, {t: compile(filt, t) for t in ("fast-convex", "cvxpy", "exact")})
    return out


@pytest.mark.parametrize("norm", [1, 2, np.inf])
def test_slack_problem_agrees_with_cvxpy_and_casadi(pair, norm):
    ocp, compiled = pair[norm]
    assert compiled["fast-convex"].backend == "direct"
    for x in STATES:
        sols = {t: c.solve({"x0": x}) for t, c in compiled.items()}
        direct = sols["fast-convex"]
        # ℓ2 slacks at the apex of ten cones: Clarabel (here and through cvxpy) stops
        # "AlmostSolved" short of the 1e-10 tolerances at some states, and says so
        assert direct.status == "optimal" or (norm == 2 and direct.success), direct.summary()
        assert verify(ocp, direct, tol=1e-6).ok, str(verify(ocp, direct, tol=1e-6))
        for t, other in sols.items():
            if other.status == "optimal" and direct.status == "optimal":
                assert close(direct.objective, other.objective), (norm, x, t, direct.summary(),
                                                                  other.summary())


def test_filter_problem_agrees_and_duals_have_the_cvxpy_signs(pair):
    ocp, compiled = pair["filter"]
    slack = pair[1][1]["cvxpy"]
    for x in STATES:
        s1 = slack.solve({"x0": x})
        params = {"x0": x, "u_p": np.array([2.0]), "xi": np.maximum(s1["xi"], 0.0),
                  "xi_N": max(float(s1["xi_N"][0]), 0.0)}
        direct, cv = compiled["fast-convex"].solve(params), compiled["cvxpy"].solve(params)
        ip = compiled["exact"].solve(params)
        assert direct.success and verify(ocp, direct, tol=1e-6).ok, direct.summary()
        if cv.status == "optimal" and direct.status == "optimal":
            assert close(direct.objective, cv.objective)
            for block in ocp.blocks:  # same sign convention (the large multipliers are
                a, b = direct.dual[block.name], cv.dual[block.name]  # unique, small may not be)
                big = np.abs(b) > 1e-1 * max(1.0, float(np.abs(b).max(initial=0.0)))
                np.testing.assert_allclose(a[big], b[big], rtol=1e-4, err_msg=block.name)
        if ip.status == "optimal":
            assert close(direct.objective, ip.objective, rel=1e-5)
            assert direct["u"][0, 0] == pytest.approx(ip["u"][0, 0], rel=1e-5, abs=1e-6)


def test_history_independence(pair):
    """The same parameters give the same answer fresh and after 100 other solves."""
    ocp, _ = pair[1]
    x = np.array([0.7, -1.3])
    fresh = compile(ocp, "fast-convex").solve({"x0": x})
    used = compile(ocp, "fast-convex")
    for y in np.random.default_rng(1).uniform([-1.0, -3.0], [1.0, 3.0], size=(100, 2)):
        used.solve({"x0": y})
    again = used.solve({"x0": x})
    np.testing.assert_array_equal(fresh.w, again.w)
    assert fresh.objective == again.objective and fresh.iterations == again.iterations


def test_parametric_vectors_equal_the_full_products(pair):
    """``b(p)`` multiplies only the rows of ``B`` with entries and ``q(p)`` skips an empty
    ``Q``: both equal the full ``b0 + B p + D φ(p)`` and ``q0 + Q p`` exactly, and repeated
    calls neither share nor change their results."""
    ocp, compiled = pair["filter"]
    prog = compiled["fast-convex"].program
    assert 0 < np.count_nonzero(np.diff(prog.B.tocsr().indptr)) < prog.B.shape[0]
    rng = np.random.default_rng(5)
    for _ in range(3):
        p = rng.normal(size=prog.B.shape[1])
        full = prog.b0 + prog.B @ p
        if prog.derived:
            full = full + prog.D @ np.array([float(f(p)) for f in prog.derived])
        got = prog.b(p)
        np.testing.assert_array_equal(got, full)
        got[:] = np.nan                      # a result of b(p) is the caller's to change
        np.testing.assert_array_equal(prog.b(p), full)
        np.testing.assert_array_equal(prog.q(p), prog.q0 + prog.Q @ p)
    q = prog.q(p)
    q[:] = np.nan
    assert np.all(np.isfinite(prog.q0))


# -- the rendezvous (§6.5), small N: Algorithm 5.2 (5.15)/(5.16) and Algorithm 6.4 (6.15) ---

@pytest.fixture(scope="module")
def rendezvous():
    from balustrade.reproduce.rendezvous import controllers, design

    d = design(N=8, T=20)
    return d, {t: controllers(d, (0.9,), target=t) for t in ("fast-convex", "cvxpy")}


def _states(d) -> list[np.ndarray]:
    x0 = np.asarray(d["setup"].x0, float)
    rng = np.random.default_rng(3)
    return [x0] + [x0 * rng.uniform(0.05, 0.6) for _ in range(3)]


def test_rendezvous_robust_pair_agrees_with_cvxpy(rendezvous):
    """(5.15) (``h_r``) and (5.16) of Algorithm 5.2: direct and cvxpy agree."""
    from balustrade.control.robust_steps import polished_slacks

    d, ctls = rendezvous
    dr, cr = ctls["fast-convex"]["robust"], ctls["cvxpy"]["robust"]
    assert dr.slack.backend == dr.filter.backend == "direct"
    checked = 0
    for x in _states(d):
        h_d, s_d = dr.h_r(x)
        h_c, s_c = cr.h_r(x)
        assert s_d.status == "optimal", s_d.summary()
        assert verify(dr.slack.ocp, s_d, tol=1e-6).ok
        if s_c.status == "optimal":
            assert close(s_d.objective, s_c.objective) and close(h_d, h_c), (x, h_d, h_c)
        xi, xi_N = polished_slacks(s_d, dr.X_E, dr.h_f, dr.deltas)
        params = {"x0": x, "u_p": np.zeros(3), "xi": xi, "xi_N": xi_N}
        f_d, f_c = dr.filter.solve(params), cr.filter.solve(params)
        assert f_d.success, f_d.summary()
        assert verify(dr.filter.ocp, f_d, tol=1e-6).ok
        if f_c.status == "optimal" and f_d.status == "optimal":
            assert close(f_d.objective, f_c.objective), (x, f_d.summary(), f_c.summary())
            checked += 1
    assert checked >= 2


def test_rendezvous_multiobjective_problem_agrees_with_cvxpy(rendezvous):
    """(6.15) of Algorithm 6.4 at a decrease bound from (5.15): direct and cvxpy agree."""
    d, ctls = rendezvous
    dm, cm = ctls["fast-convex"]["mo_rho0.9"], ctls["cvxpy"]["mo_rho0.9"]
    assert dm.problem.backend == "direct"
    checked = 0
    for x in _states(d):
        s0 = dm.slack.solve({"x0": x})
        assert s0.success, s0.summary()
        params = {"x0": x, "u_p": np.zeros(3), "bound": 1.05 * s0.objective + 1e-3}
        a, b = dm.problem.solve(params), cm.problem.solve(params)
        assert a.status == "optimal", a.summary()
        assert verify(dm.problem.ocp, a, tol=1e-6).ok
        if b.status == "optimal":
            assert close(a.objective, b.objective), (x, a.summary(), b.summary())
            checked += 1
    assert checked >= 2


# -- statuses, errors, solvers -------------------------------------------------------------

def _lp_infeasible() -> OCP:
    ocp = OCP(name="infeasible")
    u = ocp.variable("u", 1, lb=0.0)
    ocp.le(u + 1.0, 0, name="impossible")
    ocp.minimize(u[0] ** 2)
    return ocp


@pytest.mark.parametrize("target", ["fast-convex-qp", "fast-convex-conic"])
def test_infeasible_problem_is_reported_infeasible(target):
    sol = compile(_lp_infeasible(), target).solve()
    assert sol.status == "infeasible", sol.summary()
    assert np.all(np.isnan(sol.w)) and np.isnan(sol.objective)


def test_nonconvex_ocp_raises_naming_the_block():
    ocp = OCP(name="nonconvex")
    u = ocp.variable("u", 2)
    ocp.le(1.0 - u[0] ** 2 - u[1] ** 2, 0, name="outside_disc")
    ocp.minimize(u[0] ** 2 + u[1] ** 2)
    with pytest.raises(ConvexityError, match="outside_disc"):
        compile(ocp, "fast-convex")


def test_bad_parameters_raise_balustrade_errors(pair):
    direct = pair[1][1]["fast-convex"]
    with pytest.raises(BalustradeError, match="x0"):
        direct.solve({"x0": np.zeros(3)})
    with pytest.raises(BalustradeError):
        direct.solve({"nope": np.zeros(2)})


def test_solver_choice_and_targets():
    qp = OCP(name="qp")
    u = qp.variable("u", 2, lb=-1.0, ub=1.0)
    x = qp.parameter("x", 2)
    qp.le(u[0] + u[1] - 1.0, 0, name="sum")
    qp.minimize((u[0] - x[0]) ** 2 + (u[1] - x[1]) ** 2)
    assert compile(qp, "fast-convex").solver_name == "piqp"
    assert compile(qp, "direct").solver_name == "piqp"
    assert compile(qp, "fast-convex-conic").solver_name == "clarabel"
    a = compile(qp, "fast-convex").solve({"x": np.array([3.0, -2.0])})
    b = compile(qp, "fast-convex-conic").solve({"x": np.array([3.0, -2.0])})
    for s in (a, b):  # projection of (3, −2) onto the box: (1, −1), u0 + u1 = 0 < 1 inactive
        assert s.status == "optimal"
        np.testing.assert_allclose(s["u"].ravel(), [1.0, -1.0], atol=1e-7)
        assert s.dual["sum"][0] == pytest.approx(0.0, abs=1e-7)
    assert resolve_target("direct") is PRESETS["fast-convex"]
    # PIQP is history independent too (re-equilibrated on each update, cold start)
    used = compile(qp, "fast-convex-qp")
    for y in np.random.default_rng(2).normal(size=(100, 2)) * 3:
        used.solve({"x": y})
    again = used.solve({"x": np.array([3.0, -2.0])})
    np.testing.assert_array_equal(again.w, a.w)
    tube = OCP(name="tube")
    z = tube.variable("z", 2)
    tube.le(z.T @ z, 1.0)
    tube.minimize(z[0])
    with pytest.raises(SolverError, match="PIQP takes LPs and QPs only"):
        compile(tube, "fast-convex-qp")
    with pytest.raises(SolverError, match="no solver 'osqp'"):
        DirectCompiled(tube, "osqp")


def test_quadratic_row_and_epigraphs_match_by_hand():
    """min |z0 − 2| + ‖z − c‖∞ + max(z) s.t. ‖z‖² <= 1 (a rotated cone, expanded in z):
    against IPOPT; the row's multiplier against cvxpy."""
    ocp = OCP(name="epigraphs")
    z = ocp.variable("z", 2)
    c = ocp.parameter("c", 2)
    ocp.le(z.T @ z - 1.0, 0, name="disc")
    ocp.minimize(norm(z[0] - 2.0, 1) + 2.0 * norm(z - c, np.inf) + max_of(z)
                 + 0.5 * norm(z + c, 2) + 0.1 * norm(z - c, 1))
    params = {"c": np.array([0.3, 0.8])}
    a = compile(ocp, "fast-convex").solve(params)
    b = compile(ocp, "cvxpy").solve(params)
    assert a.status == "optimal" and a.objective == pytest.approx(b.objective, rel=1e-7)
    assert a.dual["disc"][0] == pytest.approx(b.dual["disc"][0], rel=1e-5, abs=1e-7)


def test_lowering_is_built_once(monkeypatch):
    """P and A are constant: only q and b depend on the parameters (the tube row of a
    parametrized centre enters b); solves set up no solver and run no lowering pass."""
    ocp = OCP(name="far_tube")
    z = ocp.variable("z", 3)
    x = ocp.parameter("x", 3)
    ocp.le((x - z).T @ (x - z), 1.0)
    ocp.minimize(z.T @ z)
    prog, _ = ToConic().apply(Classify().apply(ocp)[0])
    assert prog.B.nnz == 3 and prog.Q.nnz == 0 and prog.cones[-1] == ("soc", 4)
    compiled = compile(ocp, "fast-convex")
    import balustrade.backends.direct_backend as direct_backend

    def rebuilt(*args, **kwargs):
        raise AssertionError("a solve rebuilt the lowering or a solver")

    for name in ("make_engine", "run_chain"):
        monkeypatch.setattr(direct_backend, name, rebuilt)
    monkeypatch.setattr(direct_backend.ToConic, "apply", rebuilt)
    for xv in (np.array([1e3, -2e3, 5e2]), np.array([3.0, 0.0, 0.0])):
        sol = compiled.solve({"x": xv})
        assert sol.status == "optimal", sol.summary()
        np.testing.assert_allclose(sol["z"].ravel(), xv * (1 - 1 / np.linalg.norm(xv)),
                                   rtol=1e-7, atol=1e-7)


def test_auto_target_picks_direct_for_convex_and_exact_otherwise():
    convex = OCP(name="convex")
    u = convex.variable("u", 2, lb=-1.0, ub=1.0)
    convex.minimize(u[0] ** 2 + (u[1] - 3.0) ** 2)
    c = compile(convex, "auto")
    assert c.backend == "direct" and c.target is PRESETS["fast-convex"]
    assert c.solve().objective == pytest.approx(4.0, rel=1e-8)
    nonconvex = OCP(name="nonconvex")
    v = nonconvex.variable("v", 2, lb=-2.0, ub=2.0)
    nonconvex.le(1.0 - v[0] ** 2 - v[1] ** 2, 0, name="outside_disc")
    nonconvex.minimize((v[0] - 0.1) ** 2 + v[1] ** 2)
    n = compile(nonconvex, "auto")
    assert n.backend == "casadi" and n.target is PRESETS["exact"]
    assert n.solve().objective == pytest.approx(0.81, rel=1e-6)
    with pytest.raises(SolverError, match="auto target"):
        compile(convex, "auto", options={"max_iter": 3})


@pytest.mark.parametrize("kind", [1, np.inf])
def test_norms_of_sign_definite_rows_need_no_two_sided_epigraph(kind):
    """‖ξ‖₁ and ‖ξ‖∞ of slacks ξ >= 0 (and of −ξ): ℓ1 is linear (no epigraph variable or
    row), ℓ∞ needs one side only; a row of unknown sign (ξ − c) keeps both sides. The answer
    agrees with cvxpy and with IPOPT."""
    ocp = OCP(name="definite")
    xi = ocp.variable("xi", 3, lb=0.0)
    z = ocp.variable("z", 2)
    c = ocp.parameter("c", 3)
    ocp.le(c[0:2], xi[0:2] + z, name="cover")
    ocp.le(c[2], xi[2] - z[0] - z[1], name="cover2")
    ocp.minimize(norm(xi, kind) + 0.5 * norm(-xi[1:3], kind) + norm(z, 1)
                 + 0.1 * norm(xi - c, kind))
    prog, _ = ToConic().apply(Classify().apply(ocp)[0])
    n_w = int(ocp.decision_vector().numel())
    # ℓ1: only ‖z‖₁ (2) and ‖ξ − c‖₁ (3) need epigraph variables, 2 rows each; ℓ∞: one
    # variable per ℓ∞ term, one row per entry of ξ and of −ξ[1:3], two per entry of ξ − c
    assert prog.P.shape[0] - n_w == 5
    assert prog.A.shape[0] == 6 + (4 + 6 if kind == 1 else 3 + 2 + 4 + 6)
    for cv in (np.array([1.0, -0.5, 0.7]), np.array([-1.0, 2.0, 3.0])):
        params = {"c": cv}
        a = compile(ocp, "fast-convex").solve(params)
        b = compile(ocp, "cvxpy").solve(params)
        e = compile(ocp, "exact").solve(params)
        assert a.status == "optimal", a.summary()
        assert a.objective == pytest.approx(b.objective, rel=1e-7, abs=1e-8)
        assert a.objective == pytest.approx(e.objective, rel=1e-6, abs=1e-6)
        assert verify(ocp, a).ok


def test_a_nonfinite_optimal_answer_is_failed_not_optimal(monkeypatch):
    """A solver saying "solved" with a NaN/inf point (or multipliers) is not passed on as
    optimal: the status becomes ``failed`` and the message says why."""
    from balustrade.backends.direct_engines import RawResult

    ocp = OCP(name="box")
    u = ocp.variable("u", 2, lb=-1.0, ub=1.0)
    ocp.minimize(u[0] ** 2 + (u[1] - 3.0) ** 2)
    compiled = compile(ocp, "fast-convex")
    good = compiled.engine.run(compiled.program.q(np.zeros(0)), compiled.program.b(np.zeros(0)))
    for field in ("y", "z"):
        y, z = good.y.copy(), good.z.copy()
        (y if field == "y" else z)[0] = np.nan
        bad = RawResult(good.status, good.words, y, z, 3)
        monkeypatch.setattr(compiled.engine, "run", lambda q, b, bad=bad: bad)
        sol = compiled.solve()
        assert sol.status == "failed" and "not finite" in sol.message, (field, sol.summary())
        assert np.all(np.isnan(sol.w)) and np.isnan(sol.objective)


def test_nonfinite_multipliers_as_a_list_are_caught_without_an_array():
    """Clarabel's multipliers arrive as a Python list and are checked by their sum
    (:func:`~balustrade.backends.direct_engines.all_finite`): a NaN, an infinity or opposite
    infinities anywhere make a "solved" verdict ``failed``; a sum that overflows from finite
    entries is checked entry by entry and passes; the list becomes an array when read."""
    from balustrade.backends.direct_engines import RawResult, all_finite
    from balustrade.backends.solution import Status

    y = np.zeros(3)
    for bad in ([1.0, np.nan, 2.0], [np.inf, 1.0], [1.0, np.inf, -np.inf], [-np.inf]):
        r = RawResult(Status.OPTIMAL, "solved", y, list(bad), 4)
        assert r.status == Status.FAILED and "not finite" in r.words, bad
        assert not all_finite(bad) and not all_finite(np.array(bad))
    huge = [1e308, 1e308, -1e308]          # finite entries, overflowing sum
    assert all_finite(huge)
    r = RawResult(Status.OPTIMAL, "solved", y, huge, 4)
    assert r.status == Status.OPTIMAL
    assert isinstance(r.z, np.ndarray) and r.z.tolist() == huge
    assert all_finite([]) and not all_finite(None)


def test_block_duals_are_computed_on_read_and_copy_as_dicts():
    """The multipliers per block of a direct solve are computed when first read; they equal
    the eager computation, and a copy or a pickle of them is a plain dict."""
    import copy
    import pickle

    from balustrade.backends.direct_backend import BlockDuals

    ocp = OCP(name="box")
    u = ocp.variable("u", 2, lb=-1.0, ub=1.0)
    ocp.le(u[0] + u[1] - 0.5, 0, name="sum")
    ocp.minimize(u[0] ** 2 + (u[1] - 3.0) ** 2)
    compiled = compile(ocp, "fast-convex-conic")
    sol = compiled.solve()
    assert isinstance(sol.dual, BlockDuals) and sol.dual._blocks is None  # not yet read
    raw = compiled.engine.run(compiled.program.q(np.zeros(0)), compiled.program.b(np.zeros(0)))
    eager = compiled._duals(compiled.program, raw.z)
    assert set(sol.dual) == set(eager) and len(sol.dual) == len(eager)
    for name, values in eager.items():
        np.testing.assert_array_equal(sol.dual[name], values)
    assert sol.dual["sum"][0] > 0.1
    for twin in (copy.copy(sol.dual), copy.deepcopy(sol.dual), pickle.loads(pickle.dumps(sol))
                 .dual):
        assert type(twin) is dict and set(twin) == set(eager)
        np.testing.assert_array_equal(twin["sum"], eager["sum"])


@pytest.mark.parametrize("target", ["fast-convex-qp", "fast-convex-conic"])
def test_bad_solver_options_raise_solver_errors_naming_them(target):
    ocp = OCP(name="box")
    u = ocp.variable("u", 2, lb=-1.0, ub=1.0)
    ocp.minimize(u[0] ** 2 + (u[1] - 3.0) ** 2)
    with pytest.raises(SolverError, match="'max_iter' cannot be 'many'"):
        compile(ocp, target, options={"max_iter": "many"})
    with pytest.raises(SolverError, match="unknown .* option 'nope'"):
        compile(ocp, target, options={"nope": 1})
    with pytest.raises(SolverError, match="options must be a dict"):
        DirectCompiled(ocp, options=[("max_iter", 3)])
