"""The horizon-free approximate PCBF filter (7.5)/(7.6), Algorithms 7.5 and 8.7 (SPEC §2.28,
§2.34, §4.10) on the pendulum (7.10) with hand-written explicit ``ĥ``."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from balustrade.control.approximate import ApproximatePCBFFilter, GridPCBFFilter
from balustrade.control.decrease import DecreaseResult, MaximalDecrease, in_set
from balustrade.dsl.sets import Polytope
from balustrade.errors import BalustradeError, ShapeError
from balustrade.models.pendulum import pendulum, pendulum_setup
from balustrade.problems.approximate import (
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


@pytest.mark.parametrize("solver", ["exact", "fast-sqp"])
def test_proposition_7_3_filter_feasible_everywhere(states, solver):
    """Prop. 7.3: the (7.6) minimizer is feasible in (7.5); (7.5) solves at every state."""
    ctl = {rho: ApproximatePCBFFilter(SYS, U, h_wavy, rho=rho, target=solver, certify=False)
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
    dec = MaximalDecrease(SYS, U, h_wavy, target="exact")
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
    fast = ApproximatePCBFFilter(SYS, U, h_nonneg, rho=1.0, target="exact")
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
    f = ApproximatePCBFFilter(SYS, U, h_wavy, rho=0.3, target="exact", certify=False)
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
    f = ApproximatePCBFFilter(SYS, U, h_nonneg, target="fast-sqp")
    assert f.certifies(np.zeros(2), np.array([0.5]))
    assert not f.certifies(np.zeros(2), np.array([3.5]))  # ĥ(f(x,u_p)) <= 0 but u_p ∉ U
    u, info = f.step(np.zeros(2), np.array([3.5]))
    assert info.status == "ok" and u[0] <= 3.0 + 1e-7 and f.n_certified == 0


def test_controller_never_raises_for_runtime_data():
    """NaN/inf values fall back (state) or are read as 0 (proposal); wrong shapes and junk
    arguments are programming errors and raise a BalustradeError naming the argument."""
    f = ApproximatePCBFFilter(SYS, U, h_wavy, target="fast-sqp")
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


def reference_decrease(dec: MaximalDecrease, x: np.ndarray, u_p: np.ndarray | None = None
                       ) -> DecreaseResult:
    """The plain (7.6) multi-start the fast :meth:`MaximalDecrease.solve` must reproduce:
    candidates ``[Π_U(0), Π_U(u_p), grid]`` screened by a mapped CasADi call, every local
    solve through ``Compiled.solve`` (no buffers, no KKT-vertex shortcut, no FastNLP)."""
    nu = dec.system.nu
    u_p = np.zeros(nu) if u_p is None else np.asarray(u_p, float).reshape(nu)
    u_p_in = dec.U.project(u_p)
    cand = np.vstack([dec.U.project(np.zeros(nu)).reshape(1, nu), u_p_in.reshape(1, nu),
                      dec.grid])
    many = dec._h_next.map(len(cand))
    values = np.asarray(many(np.tile(np.reshape(x, (-1, 1)), len(cand)), cand.T)).reshape(-1)
    h_proposal = float(values[1])
    values = np.where(np.isfinite(values), values, np.inf)
    order = np.argsort(values, kind="stable")
    best_u, best_v = cand[order[0]].copy(), float(values[order[0]])
    sols, success, tried = [], False, []
    for idx in order:
        if len(tried) >= dec.n_local:
            break
        if any(np.allclose(cand[idx], t) for t in tried):
            continue
        tried.append(cand[idx])
        sol = dec.compiled.solve({"x0": x}, warm_start={"u": cand[idx]})
        sols.append(sol)
        if sol.usable:
            u_loc = np.asarray(sol["u"], float).reshape(nu)
            if np.all(np.isfinite(u_loc)) and in_set(u_loc, dec.U, 1e-7):
                v = dec.h_next(x, u_loc)
                success = success or sol.success
                if v < best_v:
                    best_u, best_v = u_loc, v
    h_x = dec.h_value(x)
    return DecreaseResult(best_u, h_x, best_v, h_x - best_v, sols,
                          success or np.isfinite(best_v), u_p_in, h_proposal, 0.0, len(tried))


class ReferenceFilter(ApproximatePCBFFilter):
    """Algorithm 7.5 with :func:`reference_decrease` and every (7.5) solve through
    ``Compiled.solve``: the reference the fast step is compared with."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.decrease.solve = lambda x, u_p=None: reference_decrease(self.decrease, x, u_p)

    def _filter(self, x, u_p, dec, info):
        return self._filter_solve(x, u_p, dec, info)


@pytest.mark.parametrize("target", ["fast-sqp", "exact"])
@pytest.mark.parametrize("h_fun", [h_wavy, h_monotone])
def test_fast_path_equals_the_compiled_solves(states, target, h_fun):
    """The step (buffered evaluations, the KKT-vertex start, :class:`FastNLP`) gives the
    answers of the reference (every local solve through ``Compiled.solve``)."""
    kw = dict(rho=0.4, target=target, certify=False)
    fast = ApproximatePCBFFilter(SYS, U, h_fun, **kw)
    slow = ReferenceFilter(SYS, U, h_fun, **kw)
    rng = np.random.default_rng(13)
    tol = 1e-12 if target == "fast-sqp" else 1e-7  # IPOPT stops near a bound, not on it
    for x in states:
        u_p = rng.uniform(-3.5, 3.5, 1)
        a, b = fast.decrease.solve(x, u_p), slow.decrease.solve(x, u_p)
        assert a.success and b.success
        assert np.abs(a.u - b.u).max() <= tol and abs(a.dh - b.dh) <= tol
        assert a.h_x == b.h_x and a.h_proposal == pytest.approx(b.h_proposal, abs=1e-14)
        (u1, i1), (u2, i2) = fast.step(x, u_p), slow.step(x, u_p)
        assert (i1.status, i1.fallback) == (i2.status, i2.fallback)
        assert np.abs(u1 - u2).max() <= (1e-9 if target == "fast-sqp" else 1e-6)
    assert (fast.n_proposal_feasible, fast.n_fallbacks) == \
        (slow.n_proposal_feasible, slow.n_fallbacks)


def test_kkt_vertex_start_is_the_solvers_answer(states):
    """Where the screened start is a vertex of ``U`` with ``∇_u ĥ(f(x, u))`` pointing out
    of ``U``, ``sqpmethod`` started there returns the start itself: skipping it is exact."""
    dec = MaximalDecrease(SYS, U, h_monotone, target="fast-sqp")
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
    f = ApproximatePCBFFilter(SYS, U, h_wavy, target="fast-sqp")
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

    kw = dict(rho=0.5, target="fast-sqp", certify=False)
    fast, slow = ApproximatePCBFFilter(sys2, U2, h2, **kw), ReferenceFilter(sys2, U2, h2, **kw)
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


def test_maximal_decrease_stays_in_a_non_box_input_set():
    """With a non-box ``U`` the screening starts are projected onto ``U`` itself: clipping
    ``0`` to the bounding box of ``U = {u₁ + u₂ >= 1, u <= 2}`` gives ``0 ∉ U``, the best
    screened value of ``ĥ(f(x, u)) = ‖u‖²``, which the multi-start returned as its
    "minimizer" before :meth:`Set.project` replaced the clip."""
    from balustrade.dsl.system import LinearSystem

    sys2 = LinearSystem(np.eye(2), np.eye(2))
    U2 = Polytope(np.array([[-1.0, -1.0], [1.0, 0.0], [0.0, 1.0]]), np.array([-1.0, 2.0, 2.0]))
    assert not U2.contains(np.clip(np.zeros(2), U2.bounding_box().lb, U2.bounding_box().ub))
    dec = MaximalDecrease(sys2, U2, lambda x: ca.sumsqr(x), target="fast-sqp")
    res = dec.solve(np.zeros(2), np.array([-3.0, -3.0]))
    assert U2.contains(res.u, tol=1e-9) and U2.contains(res.u_proposal, tol=1e-9)
    assert res.u == pytest.approx([0.5, 0.5], abs=1e-7)
    assert res.h_next == pytest.approx(0.5, abs=1e-7)


def test_acceptable_ipopt_stop_of_7_5_is_flagged_not_ok() -> None:
    """IPOPT's acceptable stop passes CasADi's ``error_on_fail``, so the fast path of (7.5)
    took it as optimal: the step said ``ok`` with nothing flagged, where ``Compiled.solve``
    of the same problem says ``optimal_inaccurate`` (audit B, session 14). The step now
    reports it as that solve does; the applied input is unchanged."""
    from balustrade.backends.targets import Target

    acc = Target("casadi", "ipopt", {"ipopt.tol": 1e-30, "ipopt.acceptable_tol": 1e-6,
                                     "ipopt.acceptable_iter": 1}, retries=(), name="acc")
    P = np.array([[4.246, 0.212], [0.212, 0.460]])
    f = ApproximatePCBFFilter(SYS, U, lambda x: ca.mtimes([x.T, ca.DM(P), x]) - 1, rho=0.5,
                              certify=False, exact_shortcut=False, target=acc)
    x, u_p = np.array([0.4, 1.0]), np.array([3.0])
    u, info = f.step(x, u_p)
    dec = f.decrease.solve(x, u_p)
    ref = f.filter.solve({"x0": x, "u_p": u_p, "dh": dec.dh, "rho": 0.5},
                         warm_start={"u": dec.u})
    assert ref.status == "optimal_inaccurate"       # the independent, plain solve
    assert info.status == "filter_optimal_inaccurate", info.status
    assert info.uncertified.get("filter") == "optimal_inaccurate"
    assert u == pytest.approx(np.asarray(ref["u"]).reshape(-1), abs=1e-8)


def test_grid_filter_refuses_a_grid_too_large_to_build() -> None:
    """half_width 1e6 at spacing 1e-6 (2e12 candidates) raised a MemoryError from numpy
    while building the offsets (audit B, session 14); now a BalustradeError naming both."""
    with pytest.raises(BalustradeError, match="half_width .* spacing .* candidate inputs"):
        GridPCBFFilter(SYS, U, h_wavy, 1e6, 1e-6)
    assert len(GridPCBFFilter(SYS, U, h_wavy, 0.5, 0.1).offsets) == 11
