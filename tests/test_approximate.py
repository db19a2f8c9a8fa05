"""The horizon-free approximate PCBF filter (7.5)/(7.6), Algorithms 7.5 and 8.7 (SPEC §2.28,
§2.34, §4.10) on the pendulum (7.10) with hand-written explicit ``ĥ``."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from reference_approximate import ReferenceApproximatePCBFFilter

from balustrade.control.approximate import ApproximatePCBFFilter, GridPCBFFilter
from balustrade.dsl.sets import Polytope
from balustrade.errors import BalustradeError, ShapeError
from balustrade.models.pendulum import pendulum, pendulum_setup
from balustrade.problems.approximate import (
    MaximalDecrease,
    approximate_filter_problem,
    as_h_function,
    decrease_bound,
    max_decrease_problem,
)

P = np.array([[4.246, 0.212], [0.212, 0.460]])


def h_wavy(x):
    """A nonconvex stand-in for a learned extended ``ĥ`` (negative inside, several minima)."""
    return ca.mtimes([x.T, P, x]) - 1 + 0.3 * ca.sin(3 * x[0]) * ca.cos(2 * x[1])


def h_nonneg(x):
    """A nonnegative stand-in for a learned ``ĥ_PB`` (zero on an ellipse)."""
    return ca.fmax(0, ca.mtimes([x.T, P, x]) - 1) ** 2


SYS = pendulum()
U = pendulum_setup().U


@pytest.fixture(scope="module")
def states() -> np.ndarray:
    rng = np.random.default_rng(7)
    return np.vstack([rng.uniform([-0.5, -1.5], [0.5, 1.5], (60, 2)),
                      rng.uniform([-2.0, -8.0], [2.0, 8.0], (40, 2))])


@pytest.mark.parametrize("solver", ["ipopt", "sqpmethod"])
def test_proposition_7_3_filter_feasible_everywhere(states, solver):
    """Prop. 7.3: the (7.6) minimizer is feasible in (7.5); (7.5) solves at every state."""
    ctl = {rho: ApproximatePCBFFilter(SYS, U, h_wavy, rho=rho, solver=solver, certify=False)
           for rho in (1.0, 0.5, 0.1)}
    h = as_h_function(h_wavy, 2)
    for rho, f in ctl.items():
        for x in states:
            dec = f.decrease.solve(x, np.zeros(1))
            assert dec.success and U.contains(dec.u, tol=1e-9)
            # the minimizer of (7.6) satisfies the decrease constraint of (7.5)
            lhs = float(h(SYS.step(x, dec.u))) - float(h(x))
            assert lhs <= decrease_bound(dec.dh, rho) + 1e-12
            u, info = f.step(x, np.array([2.5]))
            assert info.fallback is None, (x, rho, info.status)
            assert info.status in ("ok", "proposal_feasible")
            assert U.contains(u, tol=1e-7)
            bound = decrease_bound(info.values["dh"], rho)
            assert float(h(SYS.step(x, u))) - float(h(x)) <= bound + 2e-6
        assert f.n_fallbacks == 0 and f.n_solved == len(states)


def test_decrease_bound_is_the_thesis_bound_for_nonnegative_decrease():
    for rho in (1.0, 0.3):
        assert decrease_bound(0.7, rho) == pytest.approx(-rho * 0.7)
        # Δĥ < 0: the (7.6) minimizer (change −Δĥ) stays feasible for every ρ
        assert decrease_bound(-0.2, rho) == pytest.approx(0.2)
    x = ca.SX.sym("d")
    f = ca.Function("b", [x], [decrease_bound(x, 0.3)])
    assert float(f(0.5)) == pytest.approx(-0.15) and float(f(-0.5)) == pytest.approx(0.5)


def test_multistart_finds_global_minimum(states):
    dec = MaximalDecrease(SYS, U, h_wavy, solver="ipopt")
    grid = np.linspace(-3, 3, 2001)
    h = as_h_function(h_wavy, 2)
    for x in states[:40]:
        brute = min(float(h(SYS.step(x, [u]))) for u in grid[::20])
        fine = np.linspace(-3, 3, 2001)
        brute = min(brute, float(np.min(np.asarray(
            dec._h_next.map(len(fine))(np.tile(x.reshape(2, 1), len(fine)), fine.reshape(1, -1))
        ))))
        res = dec.solve(x)
        assert res.h_next <= brute + 1e-7
        assert res.dh == pytest.approx(float(h(x)) - res.h_next)


def solve_7_5(f: ApproximatePCBFFilter, x: np.ndarray, u_p: np.ndarray) -> np.ndarray:
    """(7.6) then (7.5) with the compiled solvers, no shortcut of any kind."""
    dec = f.decrease.solve(x, u_p)
    sol = f.filter.solve({"x0": x, "u_p": u_p, "dh": dec.dh, "rho": f.rho},
                         warm_start={"u": dec.u})
    assert sol.success, sol.summary()
    return np.asarray(sol["u"]).reshape(-1)


def test_certification_returns_the_solvers_answer():
    """Alg. 7.5 line 4 with ``ĥ >= 0``: whenever the shortcut fires, solving (7.6)+(7.5)
    returns ``u_p`` itself (SPEC §2.28 note); so does the exact ``u_p``-feasible shortcut."""
    rng = np.random.default_rng(3)
    fast = ApproximatePCBFFilter(SYS, U, h_nonneg, rho=1.0, solver="ipopt")
    fired = exact = 0
    for _ in range(150):
        x = rng.uniform([-0.6, -2.0], [0.6, 2.0])
        u_p = rng.uniform(-3.5, 3.5, 1)
        u_fast, info = fast.step(x, u_p)
        u_solver = solve_7_5(fast, x, u_p)
        if info.status == "certified":
            fired += 1
            assert np.array_equal(u_fast, u_p)
        exact += info.status == "proposal_feasible"
        assert u_fast == pytest.approx(u_solver, abs=2e-6), (x, u_p, info.status)
    assert fast.n_certified == fired and fast.n_proposal_feasible == exact
    assert 20 <= fired <= 140  # the test exercised both branches
    assert fast.n_solved == 150 - fired


def test_proposal_feasible_shortcut_is_the_minimizer(states):
    f = ApproximatePCBFFilter(SYS, U, h_wavy, rho=0.3, solver="ipopt", certify=False)
    rng = np.random.default_rng(11)
    seen = 0
    for x in states:
        u_p = rng.uniform(-3, 3, 1)
        u, info = f.step(x, u_p)
        if info.status == "proposal_feasible":
            seen += 1
            assert u == pytest.approx(solve_7_5(f, x, u_p), abs=2e-6)
    assert seen > 5


def test_certification_requires_u_p_in_U():
    f = ApproximatePCBFFilter(SYS, U, h_nonneg, solver="sqpmethod")
    assert f.certifies(np.zeros(2), np.array([0.5]))
    assert not f.certifies(np.zeros(2), np.array([3.5]))  # ĥ(f(x,u_p)) <= 0 but u_p ∉ U
    u, info = f.step(np.zeros(2), np.array([3.5]))
    assert info.status == "ok" and u[0] <= 3.0 + 1e-7 and f.n_certified == 0


def test_controller_never_raises_for_runtime_data():
    """NaN/inf values fall back (state) or are read as 0 (proposal); wrong shapes and junk
    arguments are programming errors and raise a BalustradeError naming the argument."""
    f = ApproximatePCBFFilter(SYS, U, h_wavy, solver="sqpmethod")
    u, info = f.step(np.array([np.nan, 0.0]), np.array([5.0]))
    assert info.fallback == "projected_proposal" and u[0] == 3.0
    assert info.status == "non_finite_state"
    x = np.array([0.2, 0.1])
    u0, info0 = f.step(x, np.array([0.0]))
    u, info = f.step(x, np.array([np.nan]))
    assert np.array_equal(u, u0) and info.values["non_finite_proposal"] == 1.0
    assert info.status.startswith("non_finite_proposal") and info.fallback == info0.fallback
    assert f.n_fallbacks == 1 and f.n_steps == 3
    with pytest.raises(ShapeError, match="ApproximatePCBFFilter.step: x"):
        f.step(np.zeros(3), np.array([1.0]))
    with pytest.raises(BalustradeError, match="ApproximatePCBFFilter.step: u_p"):
        f.step(x, "a")
    with pytest.raises(BalustradeError, match="ApproximatePCBFFilter: rho"):
        ApproximatePCBFFilter(SYS, U, h_wavy, rho="a")
    f.reset()
    assert f.n_steps == 0


def test_problems_are_written_in_the_dsl_and_check_inputs():
    ocp = max_decrease_problem(SYS, U, h_wavy)
    assert set(ocp.variables) == {"u"} and set(ocp.parameters) == {"x0"}
    ocp = approximate_filter_problem(SYS, U, h_wavy)
    assert set(ocp.parameters) == {"x0", "u_p", "dh", "rho"}
    assert [b.tag for b in ocp.blocks] == ["decrease"]
    with pytest.raises(ShapeError):
        as_h_function(lambda x: x, 2)
    with pytest.raises(BalustradeError):
        ApproximatePCBFFilter(SYS, U, h_wavy, rho=0.0)
    polytope_U = Polytope(np.array([[1.0], [-1.0]]), np.array([3.0, 3.0]))
    a = MaximalDecrease(SYS, polytope_U, h_wavy).solve(np.array([0.2, 0.1]))
    b = MaximalDecrease(SYS, U, h_wavy).solve(np.array([0.2, 0.1]))
    assert a.success and a.h_next == pytest.approx(b.h_next, abs=1e-7)


def test_grid_filter_algorithm_8_7(states):
    rho = 0.9
    g = GridPCBFFilter(SYS, U, h_wavy, half_width=0.5, spacing=0.1, rho=rho)
    assert len(g.offsets) == 11
    h = as_h_function(h_wavy, 2)
    rng = np.random.default_rng(5)
    for x in states[:60]:
        u_prev = g.u_prev.copy()
        u_p = rng.uniform(-3, 3, 1)
        u, info = g.step(x, u_p)
        assert abs(u[0] - u_prev[0]) <= 0.5 + 1e-9 and U.contains(u)  # rate limit, u ∈ U
        cand = np.clip(u_prev + g.offsets[:, 0], -3, 3)
        vals = np.array([float(h(SYS.step(x, [c]))) for c in cand])
        ok = vals <= rho * float(h(x))
        if info.fallback is None:
            assert float(h(SYS.step(x, u))) <= rho * float(h(x)) + 1e-12
            assert abs(u[0] - u_p[0]) == pytest.approx(np.min(np.abs(cand[ok] - u_p[0])))
        else:
            assert not ok.any()
            assert float(h(SYS.step(x, u))) == pytest.approx(vals.min())
    g.reset()
    assert g.u_prev[0] == 0.0


def h_monotone(x):
    """A stand-in whose (7.6) minimizer often lies at a bound of ``U`` (a tilted bowl)."""
    return h_nonneg(x) + 0.8 * x[1]


@pytest.mark.parametrize("solver", ["sqpmethod", "ipopt"])
@pytest.mark.parametrize("h_fun", [h_wavy, h_monotone])
def test_fast_path_equals_the_compiled_solves(states, solver, h_fun):
    """The fast path (buffered evaluations, the KKT-vertex start, :class:`FastNLP`) gives
    the answers of the reference (every local solve through ``Compiled.solve``)."""
    kw = dict(rho=0.4, solver=solver, certify=False)
    fast = ApproximatePCBFFilter(SYS, U, h_fun, **kw)
    slow = ReferenceApproximatePCBFFilter(SYS, U, h_fun, **kw)
    rng = np.random.default_rng(13)
    tol = 1e-12 if solver == "sqpmethod" else 1e-7  # IPOPT stops near a bound, not on it
    for x in states:
        u_p = rng.uniform(-3.5, 3.5, 1)
        a, b = fast.decrease.solve(x, u_p), slow.decrease.solve(x, u_p)
        assert a.success and b.success
        assert np.abs(a.u - b.u).max() <= tol and abs(a.dh - b.dh) <= tol
        assert a.h_x == b.h_x and a.h_proposal == pytest.approx(b.h_proposal, abs=1e-14)
        (u1, i1), (u2, i2) = fast.step(x, u_p), slow.step(x, u_p)
        assert (i1.status, i1.fallback) == (i2.status, i2.fallback)
        assert np.abs(u1 - u2).max() <= (1e-9 if solver == "sqpmethod" else 1e-6)
    assert (fast.n_proposal_feasible, fast.n_fallbacks) == \
        (slow.n_proposal_feasible, slow.n_fallbacks)


def test_kkt_vertex_start_is_the_solvers_answer(states):
    """Where the screened start is a vertex of ``U`` with ``∇_u ĥ(f(x, u))`` pointing out
    of ``U``, ``sqpmethod`` started there returns the start itself: skipping it is exact."""
    dec = MaximalDecrease(SYS, U, h_monotone, solver="sqpmethod")
    rng = np.random.default_rng(2)
    fired = 0
    for x in np.vstack([states, rng.uniform([-2.0, -8.0], [2.0, 8.0], (100, 2))]):
        res = dec.solve(x, np.zeros(1))
        for c in (np.array([3.0]), np.array([-3.0])):
            if dec._kkt_start(x, c):
                fired += 1
                sol = dec.compiled.solve({"x0": x}, warm_start={"u": c})
                assert sol.success and np.array_equal(np.asarray(sol["u"]).reshape(1), c)
        if res.n_kkt_starts:
            assert res.u[0] in (3.0, -3.0) and not res.solutions
    assert fired >= 20


def test_buffered_evaluations_equal_the_casadi_calls(states):
    f = ApproximatePCBFFilter(SYS, U, h_wavy, solver="sqpmethod")
    h = as_h_function(h_wavy, 2)
    rng = np.random.default_rng(4)
    for x in states:
        u = rng.uniform(-3, 3, 1)
        assert f.decrease.h_next(x, u) == float(f._h_next(x, u))
        assert f.decrease.h_value(x) == float(h(x))
        assert f.certifies(x, u) == (float(f._h_next(x, u)) <= 0.0)


def test_fast_path_two_inputs():
    """Two inputs (a 5 × 5 screening grid, KKT vertices in two dimensions): the fast path
    equals the compiled solves."""
    from balustrade.dsl.sets import Box
    from balustrade.dsl.system import LinearSystem

    sys2 = LinearSystem(np.array([[1.0, 0.1], [0.0, 1.0]]), np.array([[0.05, 0.0], [0.1, 0.2]]))
    U2 = Box(np.array([-1.0, -2.0]), np.array([1.0, 2.0]))

    def h2(x):
        return ca.mtimes([x.T, P, x]) - 1 + 0.4 * x[1] + 0.2 * ca.sin(2 * x[0])

    kw = dict(rho=0.5, solver="sqpmethod", certify=False)
    fast, slow = ApproximatePCBFFilter(sys2, U2, h2, **kw), \
        ReferenceApproximatePCBFFilter(sys2, U2, h2, **kw)
    rng = np.random.default_rng(21)
    kkt = 0
    for x in rng.uniform([-1.5, -3.0], [1.5, 3.0], (80, 2)):
        u_p = rng.uniform(-2.5, 2.5, 2)
        a, b = fast.decrease.solve(x, u_p), slow.decrease.solve(x, u_p)
        kkt += a.n_kkt_starts
        assert np.abs(a.u - b.u).max() <= 1e-12 and abs(a.dh - b.dh) <= 1e-12
        (u1, i1), (u2, i2) = fast.step(x, u_p), slow.step(x, u_p)
        assert i1.status == i2.status and np.abs(u1 - u2).max() <= 1e-9
    assert kkt > 0 and fast.n_proposal_feasible == slow.n_proposal_feasible
