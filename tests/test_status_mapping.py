"""Solver return codes → :class:`~balustrade.backends.Status`, the same in Python and in
the emitted C (issue #14, "no wrong answers").

sqpmethod with HPIPM (``structured-sqp``) stopped inside its QPs. sqpmethod declares
convergence on primal infeasibility and ``‖∇L‖`` at its last QP's multipliers and never tests
complementarity; HPIPM (interior point) stopped at ``iter_max`` returns central-path
multipliers, and sqpmethod then reported ``optimal`` with ``v_0`` of the RAPSF QP (4.5) up
to 3.8e-3 off the optimum. The backend now fails such a run
(``casadi_backend.SQP_COMPLEMENTARITY_TOL``); HPIPM's own status is no usable signal (at the
default tolerances it reports failure on every QP of these cases, accurate or not).

fatrop's acceptable stop (``StopAtAcceptablePoint``: its acceptable tolerance held for
``acceptable_iter`` iterations, the requested one not met). The emitted C cannot tell it
from a failure (its fatrop returns nonzero unless fatrop ended with ``Success``,
``backends.emittable.STATUS_OPTIONS``), so it retries it and, when no retry converges,
reports the primal-feasible point as ``BAL_FEASIBLE``. The backend reads the same return
the same way: not a success, retried, then ``feasible`` when the point is primal feasible
(the PCBF step then takes its cost only as an upper bound on ``h_PB``), never
``optimal_inaccurate`` (which the step would use as ``h_PB``). The test target forces the
stop: ``tolerance`` 1e-16 (never met), ``tol_acceptable`` 1e-6 with ``acceptable_iter`` 1.
"""

from __future__ import annotations

import numpy as np
import pytest

from balustrade.backends import compile
from balustrade.backends.targets import Target
from balustrade.control import PCBFSafetyFilter
from balustrade.dsl.sets import Box
from balustrade.examples.pendulum import pendulum_terminal_cbf
from balustrade.models.pendulum import pendulum, pendulum_setup
from balustrade.problems.pcbf import pcbf_filter_problem, pcbf_slack_problem
from balustrade.problems.rapsf import rapsf_problem, s_constants

#: fatrop stopping at its acceptable level (fatrop 1.1.8 option names), no retry: the
#: acceptable stop is the final answer of each solve, in Python and in C
ACCEPTABLE = Target("casadi", "fatrop",
                    {"fatrop": {"print_level": 0, "max_iter": 300, "tolerance": 1e-16,
                                "tol_acceptable": 1e-6, "acceptable_iter": 1}},
                    retries=(), name="fatrop-acceptable")
STATES = ([0.5, -0.3], [0.0, 0.0], [-0.8, 0.6], [0.3, 0.2], [-0.2, -0.4])


def _filter(target: Target = ACCEPTABLE) -> PCBFSafetyFilter:
    system, s = pendulum(), pendulum_setup()
    args = (system, s.X, s.U, pendulum_terminal_cbf(), s.N, s.deltas)
    slack = compile(pcbf_slack_problem(*args, alpha_f=s.alpha_f, slack_norm=1), target)
    return PCBFSafetyFilter(slack, compile(pcbf_filter_problem(*args), target), s.U)


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    from balustrade.codegen import accelerate

    py = _filter()
    c = accelerate(py, build_dir=tmp_path_factory.mktemp("acceptable"), name="accpcbf",
                   werror=True)
    return py, c


def test_fatrop_acceptable_stop_is_not_a_success():
    """The forced stop happens (message), and it is reported ``feasible`` (primal feasible,
    no convergence), never as a success: not ``optimal``, not ``optimal_inaccurate``."""
    slack = _filter().slack
    stops = 0
    for x in STATES:
        sol = slack.solve({"x0": x})
        if "StopAtAcceptablePoint" not in sol.message:
            continue
        stops += 1
        assert not sol.success, (x, sol.status)
        assert sol.status == ("feasible" if slack._primal_feasible(sol.raw["x"], sol.p)
                              else "failed"), (x, sol.status, sol.message)
    assert stops >= 3


def test_fatrop_acceptable_stop_c_equals_python(pair):
    """One step per state from a reset: the C step and the Python step agree on the
    statuses, fallbacks, uncertified solves and ``h_PB``/``h_PB_upper`` at the forced
    acceptable stops."""
    py, c = pair
    stops = 0
    for x in STATES:
        py.reset()
        c.reset()
        (u_py, a), (u_c, b) = py.step(np.asarray(x), np.array([1.0])), \
            c.step(np.asarray(x), np.array([1.0]))
        stops += "StopAtAcceptablePoint" in a.solutions["slack"].message
        assert (a.status, a.fallback, a.uncertified) == (b.status, b.fallback,
                                                         b.uncertified), x
        for key in ("h_PB", "h_PB_upper"):
            if key in a.values or key in b.values:
                np.testing.assert_allclose(b.values.get(key, np.nan),
                                           a.values.get(key, np.nan), atol=1e-6,
                                           equal_nan=True)
        np.testing.assert_allclose(u_c, u_py, atol=1e-6)
    assert stops >= 3


def _rapsf_cases(t, count: int, seed: int = 11):
    """States and boxes inside Θ₀ (vertex data as parameters) for the RAPSF toy."""
    rng = np.random.default_rng(seed)
    for _ in range(count):
        lo = rng.uniform(t.Theta0.lb, t.Theta0.ub)
        hi = rng.uniform(lo, t.Theta0.ub)
        V = Box(lo, hi).vertices()
        yield {"x0": rng.uniform(-1.5, 1.5, 2), "u_p": rng.uniform(-3, 3, 1),
               "theta": V.T, "s": s_constants(t.X0, t.sys, t.K, V)}


def test_sqp_with_hpipm_stopped_early_is_never_a_false_optimal(rapsf_toy):
    """HPIPM capped at 6 or 10 iterations per QP (no retry): every ``optimal`` run has the
    optimum's ``v_0`` to sqpmethod's dual tolerance (1e-6; old mapping: 3.8e-3 and 2.8e-4
    off), and at least one run is refused for its multipliers, never reported optimal."""
    t, N = rapsf_toy, 6
    exact = compile(rapsf_problem(t.sys, t.X0, t.F, t.G, t.W, t.K, N), "exact")
    cases = list(_rapsf_cases(t, 18))
    refs = [exact.solve(c) for c in cases]
    refused = solved = 0
    for iters in (6, 10):
        capped = Target("casadi", "sqpmethod",
                        {"qpsol": "hpipm", "qpsol_options": {"hpipm": {"iter_max": iters}}},
                        retries=(), name=f"hpipm-{iters}")
        hp = compile(rapsf_problem(t.sys, t.X0, t.F, t.G, t.W, t.K, N, staged=True), capped)
        for params, ref in zip(cases, refs):
            assert ref.status == "optimal"
            sol = hp.solve(params)
            refused += "not complementary" in sol.message
            if sol.status == "optimal":
                solved += 1
                assert abs(sol["v"][0, 0] - ref["v"][0, 0]) <= 2e-6, (iters, params["x0"])
            else:
                assert not sol.success
    assert refused >= 1 and solved >= 5


def test_sqp_with_osqp_stopped_early_is_never_a_false_optimal(rapsf_toy):
    """The same with OSQP (ADMM) capped at 25 iterations on the plain (4.5) (old mapping:
    "optimal" 4.5e-2 off)."""
    t, N = rapsf_toy, 6
    ocp = rapsf_problem(t.sys, t.X0, t.F, t.G, t.W, t.K, N)
    exact = compile(ocp, "exact")
    capped = compile(ocp, Target("casadi", "sqpmethod",
                                 {"qpsol": "osqp", "qpsol_options": {"osqp": {"max_iter": 25}}},
                                 retries=(), name="osqp-25"))
    refused = solved = 0
    for params in _rapsf_cases(t, 18):
        ref, sol = exact.solve(params), capped.solve(params)
        assert ref.status == "optimal"
        refused += "not complementary" in sol.message
        if sol.status == "optimal":
            solved += 1
            assert abs(sol["v"][0, 0] - ref["v"][0, 0]) <= 2e-6, params["x0"]
        else:
            assert not sol.success
    assert refused >= 1 and solved >= 5




def test_sqp_with_osqp_stopped_early_c_equals_python(tmp_path):
    """The emitted step's KKT test includes the backend's complementarity test (weighted
    into ``du_inf``, ``codegen.emit.complementarity_weight``): where Python refuses an
    "optimal" of sqpmethod + OSQP capped at 150 iterations (pendulum pair, no retry), the C
    does too — the same statuses on those steps (without the weight the C said ``ok``), the
    same fallbacks and inputs on all. (A solve that did not converge is ``max_iterations``
    in Python and ``not_converged`` in C: the C cannot tell why; not compared here.) Since
    the test skips equality rows and rounding-level slacks (session 11) no solve of this pair
    is refused any more (the refusals were at ``h_PB`` 1e-8 against 0); both sides use one
    expression (``casadi_backend.complementarity_expr``), checked against an independent
    computation in :func:`test_complementarity_matches_an_independent_computation`."""
    from balustrade.codegen import accelerate

    py = _filter(Target("casadi", "sqpmethod",
                        {"qpsol": "osqp", "qpsol_options": {"osqp": {"max_iter": 150}}},
                        retries=(), name="osqp-150"))
    c = accelerate(py, build_dir=tmp_path, name="oscap", werror=True)
    rng = np.random.default_rng(0)
    refused = 0
    for x in pendulum_setup().X.sample(20, rng):
        u_p = rng.uniform(-3.0, 3.0, 1)
        py.reset()
        c.reset()
        (u_py, a), (u_c, b) = py.step(x, u_p), c.step(x, u_p)
        assert (a.fallback, a.uncertified) == (b.fallback, b.uncertified), x
        np.testing.assert_allclose(u_c, u_py, atol=1e-6)
        if any("not complementary" in s.message for s in a.solutions.values()):
            refused += 1
            assert a.status == b.status, x


def test_converged_hpipm_solves_with_large_multipliers_are_accepted():
    """The complementarity test must not fail converged solves (review, session 11): with
    HPIPM no objective scaling applies, and the pendulum (2.24)'s ``α_f`` gives multipliers
    up to 3e8, so a rounding-level slack (or the primal residual of an equality row) times
    ``|λ|`` exceeded the tolerance; 9 of these 40 states (objectives equal to IPOPT's to
    4e-12) were failed and answered by the IPOPT retry. Each must be answered by sqpmethod
    itself, at IPOPT's optimum."""
    system, s = pendulum(), pendulum_setup()
    args = (system, s.X, s.U, pendulum_terminal_cbf(), s.N, s.deltas)
    ocp = pcbf_slack_problem(*args, alpha_f=s.alpha_f, slack_norm=1)
    hp, exact = compile(ocp, "structured-sqp"), compile(ocp, "exact")
    rng = np.random.default_rng(0)
    states = [np.array([1.84662877, 2.69747929])] + [rng.uniform([-2, -6], [2, 6])
                                                     for _ in range(39)]
    for x in states:
        sol, ref = hp.solve({"x0": x}), exact.solve({"x0": x})
        assert sol.status == "optimal" and sol.solver == "sqpmethod", (x, sol.message)
        assert abs(sol.objective - ref.objective) <= 1e-6 * (1 + abs(ref.objective))


def _reference_complementarity(c, w, g, lam_x, lam_g) -> float:
    """``max |λ_i| · gap_i`` written out in NumPy, independently of
    ``casadi_backend.complementarity_expr``: the feasible-side slack to the bound the sign of
    ``λ_i`` points to less 1e-12·(1 + |bound|), 1 for an infinite bound, equality rows
    skipped."""
    worst = 0.0
    for lam, val, lo, up in ((lam_x, w, c.lbx, c.ubx), (lam_g, g, c.lbg, c.ubg)):
        lo = np.broadcast_to(np.asarray(lo, float), lam.shape)
        up = np.broadcast_to(np.asarray(up, float), lam.shape)
        for i in np.flatnonzero((lam != 0) & (lo != up)):
            bound, slack = (up[i], up[i] - val[i]) if lam[i] > 0 else (lo[i], val[i] - lo[i])
            gap = max(slack - 1e-12 * (1 + abs(bound)), 0.0) if np.isfinite(bound) else 1.0
            worst = max(worst, abs(lam[i]) * gap)
    return worst


def test_complementarity_matches_an_independent_computation():
    """The complementarity term shared by the backend and the emitted KKT test
    (``casadi_backend.complementarity_expr``, evaluated by ``CasadiCompiled._complementarity``)
    equals an independent NumPy computation at random primal-dual points of the pendulum
    (2.24) with rows put on their bounds, just inside them, beyond them and with
    multipliers of both signs — equality rows, infinite bounds and the rounding allowance
    included."""
    system, s = pendulum(), pendulum_setup()
    args = (system, s.X, s.U, pendulum_terminal_cbf(), s.N, s.deltas)
    c = compile(pcbf_slack_problem(*args, alpha_f=s.alpha_f, slack_norm=1),
                Target("casadi", "sqpmethod", {"qpsol": "osqp"}, retries=(), name="osqp"))
    n, m = np.size(c.lbx), np.size(c.lbg)
    p = np.array([0.3, -0.2])
    rng = np.random.default_rng(3)
    lbx, ubx = np.asarray(c.lbx, float), np.asarray(c.ubx, float)
    assert np.any(lbx == ubx) or np.any(np.asarray(c.lbg) == np.asarray(c.ubg))
    seen = set()
    for k in range(200):
        w = rng.normal(size=n)
        on = rng.random(n) < 0.5
        offset = rng.choice([0, 1e-14, -1e-9, -1e-3], n)
        w = np.where(on & np.isfinite(ubx), ubx + offset, w)
        lam_x = rng.normal(size=n) * rng.choice([0, 1, 1e8], n)
        lam_g = rng.normal(size=m) * rng.choice([0, 1, 1e8], m)
        if k % 2:  # complementary: multipliers only on upper bounds met to rounding
            lam_x = np.where(on & np.isfinite(ubx) & (offset >= 0), np.abs(lam_x), 0.0)
            lam_g = np.zeros(m)
        py = c._complementarity(w, {"lam_x": lam_x, "lam_g": lam_g}, p)
        cc = _reference_complementarity(c, w, c._g(w, p), lam_x, lam_g)
        assert cc == pytest.approx(py, rel=1e-12, abs=1e-300), (py, cc)
        seen.add(py > 1e-8)
    assert seen == {True, False}  # the points cover both verdicts


def test_stale_solve_succeeded_without_success_is_failed():
    """CasADi 3.8.2's sqpmethod can end a run with ``success`` False while ``return_status``
    still says ``Solve_Succeeded`` from an earlier run of the same solver (session 15): such
    a run is ``failed``; a real success and IPOPT's acceptable stop keep their statuses."""
    from balustrade.backends.casadi_backend import _message, _status
    from balustrade.backends.solution import Status

    stale = {"return_status": "Solve_Succeeded", "success": False}
    assert _status(stale) == Status.FAILED
    assert "stale" in _message(stale)
    assert _status({"return_status": "Solve_Succeeded", "success": True}) == Status.OPTIMAL
    assert _status({"return_status": "Solved_To_Acceptable_Level", "success": True}) == \
        Status.OPTIMAL_INACCURATE


def test_lane_seed41_filter_is_not_a_false_optimal():
    """The lane change, Algorithm 5.2, seed 41, steps 0–10: every solve reported ``optimal``
    meets its rows to 1e-8 (``_primal_residual``, computed from the point, not from the
    solver's word). At step 10 the (5.16) SQP used to stop after one iteration off its rows
    by 8.1e-7 with a stale ``Solve_Succeeded`` and was applied as optimal (the C retried and
    applied a point of lower cost); fails on the old status mapping."""
    from balustrade.backends.solution import Status
    from balustrade.reproduce import lane_change as lc

    d = lc.design(lc.config("converging"))
    ctrl = lc.controllers(d, rho=lc.config("converging").rho)["robust"]
    ctrl.reset()
    x, ws = lc.X0.copy(), lc.disturbances(d, 41, lc.STEPS)
    for k in range(11):
        u, info = ctrl.step(x, lc.human(x))
        for name, sol in info.solutions.items():
            if sol.status == Status.OPTIMAL:
                prob = ctrl.slack if name == "slack" else ctrl.filter
                res = prob._primal_residual(sol.raw["x"], sol.p)
                assert res <= 1e-8, (k, name, res, sol.message)
        x = d.system.step(x, u, ws[k])
