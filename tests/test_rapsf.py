"""The homothetic-tube RAPSF (thesis Chapter 4, SPEC §2.18, §2.20, §2.21) on a 2-state toy
with two uncertain parameters (spring and damping of a discretized mass), Θ₀ a box, and
a short run of the 3-mass chain of §4.7; parameter sets from ``estimate.BoxUpdate``."""

from __future__ import annotations

import itertools
from types import SimpleNamespace

import casadi as ca
import numpy as np
import pytest

from balustrade.backends import compile
from balustrade.control.rapsf import RAPSF
from balustrade.design.rapsf import (
    check_assumption_4_11,
    check_constraints,
    check_rpi,
    contraction_factor,
    contractive_polytope,
    robust_gain,
)
from balustrade.dsl.sets import Box, Polytope
from balustrade.errors import BalustradeError, EmptySetError, ShapeError
from balustrade.estimate import BoxUpdate
from balustrade.models.msd import msd_chain, msd_performance, msd_setup
from balustrade.problems.rapsf import (
    TerminalSet,
    joint_constraints,
    model_matrices,
    rapsf_problem,
    s_constants,
    tube_constants,
)

N = 8


@pytest.fixture(scope="module")
def toy(rapsf_toy) -> SimpleNamespace:
    return rapsf_toy             # tests/conftest.py


# -- the QP (4.5) ------------------------------------------------------------------------------
def test_backends_agree_and_parametric_equals_constant(toy):
    ocp = rapsf_problem(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, vertices=toy.V)
    par = rapsf_problem(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N)
    s = s_constants(toy.X0, toy.sys, toy.K, toy.V)
    for x, u_p in [(np.array([1.5, 1.0]), np.array([3.0])), (np.array([-0.3, 0.4]),
                                                             np.array([-5.0]))]:
        v0 = []
        for tg in ("exact", "cvxpy", "fast-convex"):
            sol = compile(ocp, tg).solve({"x0": x, "u_p": u_p})
            assert sol.status == "optimal", tg
            v0.append(sol["v"][:, 0])
        sol = compile(par, "exact").solve({"x0": x, "u_p": u_p, "theta": toy.V.T, "s": s})
        assert sol.status == "optimal"
        v0.append(sol["v"][:, 0])
        assert np.ptp(np.array(v0)) < 1e-4 * max(1.0, float(np.abs(v0[0]).max())), v0
        assert v0[0][0] + (toy.K @ x)[0] != pytest.approx(u_p[0])   # the filter is active


def _worst_tube_violation(t: SimpleNamespace, sol, Theta: Polytope, rng) -> tuple[float, float]:
    """Brute force: sampled and extreme x ∈ z_i ⊕ α_i 𝕏₀, θ ∈ Θ, w ∈ W propagated with
    u = Kx + v_i; the largest violation of x⁺ ∈ z_{i+1} ⊕ α_{i+1}𝕏₀ and of (x, u) ∈ 𝒵."""
    z, a, v = sol["z"], sol["alpha"].ravel(), sol["v"]
    HX = t.X0.H / t.X0.h[:, None]
    xv = t.X0.vertices()
    lam = rng.dirichlet(np.ones(len(xv)), 40)
    ys = np.vstack([xv, lam @ xv])                      # points of 𝕏₀: vertices and inside
    thetas = np.vstack([Theta.vertices(), rng.uniform(Theta.lb, Theta.ub, (10, Theta.dim))])
    ws = np.vstack([t.W.vertices(), rng.uniform(t.W.lb, t.W.ub, (10, 2))])
    worst_tube, worst_z = -np.inf, -np.inf
    for i in range(v.shape[1]):
        X = z[:, i] + a[i] * ys
        U = X @ t.K.T + v[:, i]
        worst_z = max(worst_z, float(np.max(X @ t.F.T + U @ t.G.T - 1)))
        for th in thetas:
            A, B = model_matrices(t.sys, th)
            Xn = X @ A.T + U @ B.T
            for w in ws:
                lhs = (Xn + w - z[:, i + 1]) @ HX.T
                worst_tube = max(worst_tube, float(np.max(lhs - a[i + 1])))
    return worst_tube, worst_z


def test_solution_meets_vertex_conditions_by_brute_force(toy):
    rng = np.random.default_rng(3)
    Theta = Box([0.7, 0.1], [1.1, 0.3])                 # a learned Θ_k ⊂ Θ₀
    V = Theta.vertices()
    par = rapsf_problem(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N)
    s = s_constants(toy.X0, toy.sys, toy.K, V)
    solver = compile(par, "exact")
    for x, u_p in [(np.array([0.8, 0.3]), np.array([3.0])), (np.array([-0.5, 0.1]),
                                                             np.array([-3.0]))]:
        sol = solver.solve({"x0": x, "u_p": u_p, "theta": V.T, "s": s})
        assert sol.status == "optimal"
        tube, cons = _worst_tube_violation(toy, sol, Theta, rng)
        assert tube <= 1e-6 and cons <= 1e-6, (tube, cons)
    # random feasible points with tight tubes: min Σα_i + a random linear term in (z, v)
    for seed in range(2):
        c = np.random.default_rng(seed).normal(size=(2, 2 * N + 1))
        tight = rapsf_problem(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N)
        z, a, v = (tight.variables[k].sym for k in ("z", "alpha", "v"))
        tight.minimize(ca.sum2(a) + 0.01 * (ca.dot(ca.DM(c[:, :N + 1]), z)
                                            + ca.dot(ca.DM(c[:1, N + 1:]), v)))
        sol = compile(tight, "exact").solve({"x0": np.array([0.4, -0.2]),
                                             "u_p": np.array([0.0]), "theta": V.T, "s": s})
        assert sol.status == "optimal"
        tube, cons = _worst_tube_violation(toy, sol, Theta, rng)
        assert -1e-3 < tube <= 1e-6 and cons <= 1e-6, (tube, cons)       # tight, and inside
    # negative control: a support constant too small by 40 % breaks containment
    bad = solver.solve({"x0": np.array([0.8, 0.3]), "u_p": np.array([3.0]),
                        "theta": V.T, "s": 0.6 * s})
    assert bad.status == "optimal"
    tube, _ = _worst_tube_violation(toy, bad, Theta, rng)
    assert tube > 1e-3


def test_constants_are_support_functions(toy):
    c = tube_constants(toy.X0, toy.W, toy.sys, toy.K, toy.V, toy.F, toy.G)
    xv = toy.X0.vertices()
    for j, th in enumerate(toy.V):
        A, B = model_matrices(toy.sys, th)
        assert np.allclose(c.s[:, j], np.max(c.HX @ (A + B @ toy.K) @ xv.T, axis=1), atol=1e-7)
    assert np.allclose(c.t, np.max((toy.F + toy.G @ toy.K) @ xv.T, axis=1), atol=1e-7)
    assert np.allclose(c.w_bar, np.max(c.HX @ toy.W.vertices().T, axis=1))
    by_vertices = s_constants(toy.X0, toy.sys, toy.K, toy.V, X0_vertices=xv)
    assert np.allclose(by_vertices, c.s, atol=1e-7)                  # LPs == vertex maxima


# -- offline design and Assumption 4.11 -------------------------------------------------------
def test_design_satisfies_assumption_4_11(toy):
    assert contraction_factor(toy.X0, toy.sys, toy.K, toy.V) < 1
    assert check_rpi(toy.X0, toy.sys, toy.K, toy.V, toy.W)
    assert check_constraints(toy.X0, toy.F, toy.G, toy.K)
    assert check_assumption_4_11(toy.sys, toy.X0, toy.W, toy.K, toy.V, toy.F, toy.G)
    small = TerminalSet(np.vstack([np.eye(2), -np.eye(2)]) / 0.05, np.full(4, 1.0))
    assert check_assumption_4_11(toy.sys, toy.X0, toy.W, toy.K, toy.V, toy.F, toy.G, small)


def test_checks_reject_bad_designs(toy):
    tiny = Box.symmetric(1e-3, 2)                        # W does not fit: not RPI
    assert not check_rpi(tiny, toy.sys, toy.K, toy.V, toy.W)
    big = Box.symmetric(10.0, 2)                          # leaves 𝒵
    assert not check_constraints(big, toy.F, toy.G, toy.K)
    with pytest.raises(BalustradeError, match="W is too large"):
        contractive_polytope(toy.sys, toy.K, toy.V, Box.symmetric(0.5, 2), toy.F, toy.G)


def test_bad_input_names_argument(toy):
    bad = SimpleNamespace(A0=np.eye(2), A_list=[np.eye(3), np.eye(2)], B0=np.ones((2, 1)),
                          B_list=[np.zeros((2, 1))] * 2)
    with pytest.raises(ShapeError, match="A_list"):
        rapsf_problem(bad, toy.X0, toy.F, toy.G, toy.W, toy.K, N)
    with pytest.raises(BalustradeError, match="Theta0"):
        RAPSF(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, Box([0.0], [1.0]))
    with pytest.raises(BalustradeError, match="not robustly invariant"):   # non-contractive
        RAPSF(toy.sys, Box.symmetric(1e-3, 2), toy.F, toy.G, toy.W, toy.K, N, toy.Theta0)
    with pytest.raises(BalustradeError, match="leaves"):
        RAPSF(toy.sys, toy.X0, 10 * toy.F, 10 * toy.G, toy.W, toy.K, N, toy.Theta0)
    with pytest.raises(BalustradeError, match="affine in θ"):
        rapsf_problem(object(), toy.X0, toy.F, toy.G, toy.W, toy.K, N)


# -- Algorithm 4.1 ------------------------------------------------------------------------------
def _run(t, theta_star, seed, steps=25, target="exact", vertex_w=False, shrinking=False):
    rng = np.random.default_rng(seed)
    ctrl = RAPSF(t.sys, t.X0, t.F, t.G, t.W, t.K, N, t.Theta0,
                 estimator=BoxUpdate(t.sys, t.W, t.Theta0), target=target,
                 shrinking=shrinking)
    A, B = model_matrices(t.sys, theta_star)
    x = np.array([0.9, 0.2])
    thetas, worst = [t.Theta0], -np.inf
    for k in range(steps):
        u_p = np.array([3.0 * np.sin(0.4 * k) + 1.5])   # aggressive: often unsafe
        u, info = ctrl.step(x, u_p)
        worst = max(worst, float(np.max(t.F @ x + t.G @ u - 1)))
        T = ctrl.Theta
        assert T.contains(theta_star, tol=1e-7)                        # θ* ∈ Θ_k
        assert np.all(thetas[-1].contains_many(T.vertices(), tol=1e-9))  # Θ_k ⊆ Θ_{k−1}
        thetas.append(T)
        w = rng.choice([-1.0, 1.0], 2) if vertex_w else rng.uniform(-1, 1, 2)
        x = A @ x + B @ u + 0.004 * w
    return ctrl, worst, thetas


@pytest.mark.parametrize("seed", range(3))
def test_closed_loop_constraints_and_nesting(toy, seed):
    rng = np.random.default_rng(100 + seed)
    corners = toy.Theta0.vertices()
    for theta_star, vertex_w in [(rng.uniform(toy.Theta0.lb, toy.Theta0.ub), False),
                                 (corners[seed % len(corners)], True)]:
        ctrl, worst, thetas = _run(toy, theta_star, seed, vertex_w=vertex_w)
        assert worst <= 1e-6
        assert np.prod(thetas[-1].ub - thetas[-1].lb) < np.prod(toy.Theta0.ub - toy.Theta0.lb)


def test_closed_loop_on_fast_convex_matches_exact(toy):
    theta = np.array([0.9, 0.2])
    _, worst, th_e = _run(toy, theta, 7, steps=10, target="exact")
    _, worst_d, th_d = _run(toy, theta, 7, steps=10, target="fast-convex")
    assert worst <= 1e-6 and worst_d <= 1e-6
    assert np.allclose(th_e[-1].lb, th_d[-1].lb, atol=1e-5)


def test_stored_plan_then_backup(toy):
    ctrl = RAPSF(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, toy.Theta0)
    x = np.array([0.5, 0.1])
    u, info = ctrl.step(x, np.array([2.0]))
    assert info.fallback is None and ctrl.k_inf == 0
    plan = ctrl.plan.copy()
    far = np.array([5.0, 5.0])                                       # outside every tube
    for k in range(1, N):
        u, info = ctrl.step(far, np.array([0.0]))
        assert info.fallback == "stored_plan" and info.status != "ok"
        assert "rapsf" in info.uncertified
        assert np.allclose(u, toy.K @ far + plan[:, k])              # tube feedback on x_k
    u, info = ctrl.step(far, np.array([0.0]))
    assert info.fallback == "backup" and np.allclose(u, toy.K @ far)


def test_backup_at_start_and_shrunk_horizon(toy):
    ctrl = RAPSF(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, toy.Theta0, shrinking=True,
                 backup=lambda x, u_p, k: np.array([-1.0]))
    u, info = ctrl.step(np.array([5.0, 5.0]), np.array([0.0]))       # k_inf = N − 1 at start
    assert info.fallback == "backup" and u[0] == -1.0
    ctrl.step(np.array([0.5, 0.1]), np.array([2.0]))
    u, info = ctrl.step(np.array([5.0, 5.0]), np.array([0.0]))
    assert "rapsf_shrunk" in info.solutions                          # Remark 4.6 tried
    assert info.fallback in ("shrunk_horizon", "stored_plan")


class _Falsifying:
    def update(self, xp, up, x):
        return None


class _Growing:
    def update(self, xp, up, x):
        return Box([0.0, -1.0], [2.0, 1.0])


def test_falsified_model_and_non_nested_estimator(toy):
    ctrl = RAPSF(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, toy.Theta0,
                 estimator=_Falsifying())
    ctrl.step(np.array([0.5, 0.1]), np.array([1.0]))
    u, info = ctrl.step(np.array([0.5, 0.1]), np.array([1.0]))
    assert info.status == "model_falsified" and info.fallback == "backup"
    ctrl = RAPSF(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, toy.Theta0,
                 estimator=_Growing())
    ctrl.step(np.array([0.5, 0.1]), np.array([1.0]))
    u, info = ctrl.step(np.array([0.5, 0.1]), np.array([1.0]))
    assert info.status == "theta_not_nested" and ctrl.Theta is toy.Theta0
    assert info.fallback is None


def test_vertex_padding_keeps_one_compiled_problem(toy):
    ctrl = RAPSF(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, toy.Theta0)
    ctrl.step(np.array([0.5, 0.1]), np.array([1.0]))
    ctrl._set_theta(Box([0.9, 0.2], [0.9, 0.2]))        # a single point: 1 vertex, padded
    u, info = ctrl.step(np.array([0.5, 0.1]), np.array([1.0]))
    assert info.fallback is None and len(ctrl._compiled) == 1
    assert list(itertools.islice(ctrl._compiled, 1))[0] == (N, 4)


def test_falsified_by_data_outside_theta0(toy):
    """θ* outside Θ₀: the estimator finds Δ_k ∩ Θ_{k−1} empty; the filter says so and uses
    the backup policy."""
    ctrl = RAPSF(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, toy.Theta0,
                 estimator=BoxUpdate(toy.sys, toy.W, toy.Theta0))
    A, B = model_matrices(toy.sys, np.array([4.0, 2.0]))
    x, statuses = np.array([0.5, 0.3]), []
    for _ in range(4):
        u, info = ctrl.step(x, np.array([0.0]))
        statuses.append(info.status)
        x = A @ x + B @ u
    assert "model_falsified" in statuses and ctrl.falsified
    assert info.fallback == "backup"


def test_msd_three_masses_short_run():
    """§4.7 chain, 3 masses: design by LMI + contractive polytope, 20 steps of the aggressive
    controller with the box update; (x, u) ∈ 𝒵 and θ* ∈ Θ_k ⊆ Θ_{k−1}."""
    sys_, st = msd_chain(3), msd_setup(3)
    V = st.Theta0.vertices()
    F, G = joint_constraints(st.X, st.U)
    K = robust_gain(sys_, V, contraction=0.95)
    X0 = contractive_polytope(sys_, K, V, st.W, F, G)
    assert check_assumption_4_11(sys_, X0, st.W, K, V, F, G)
    rng = np.random.default_rng(5)
    theta = st.sample_theta(rng)
    ctrl = RAPSF(sys_, X0, F, G, st.W, K, st.N, st.Theta0,
                 estimator=BoxUpdate(sys_, st.W, st.Theta0), target="fast-convex")
    x, prev = st.x0.copy(), st.Theta0
    for k in range(20):
        u, info = ctrl.step(x, msd_performance(k, x, 3))
        assert np.all(F @ x + G @ u <= 1 + 1e-6), k
        assert ctrl.Theta.contains(theta, tol=1e-7)
        assert np.all(prev.contains_many(ctrl.Theta.vertices(), tol=1e-9))
        prev = ctrl.Theta
        x = sys_.step(x, u, theta, rng.uniform(-1e-3, 1e-3, 6))
    assert np.prod(prev.ub - prev.lb) < np.prod(st.Theta0.ub - st.Theta0.lb)
    ctrl.reset()                                             # back to Θ₀, estimator included
    assert ctrl.Theta is st.Theta0 and ctrl.estimator.Theta is st.Theta0 and ctrl.plan is None


@pytest.mark.slow
def test_fifty_seeded_runs_keep_constraints(toy):
    """50 seeded runs: θ* at a vertex of Θ₀ (every other run) or uniform in Θ₀, vertex or
    uniform disturbances; (x, u) ∈ 𝒵 at every step and θ* ∈ Θ_k ⊆ Θ_{k−1} (in :func:`_run`)."""
    corners = toy.Theta0.vertices()
    for seed in range(50):
        rng = np.random.default_rng(1000 + seed)
        theta = (corners[seed % len(corners)] if seed % 2 == 0
                 else rng.uniform(toy.Theta0.lb, toy.Theta0.ub))
        _, worst, _ = _run(toy, theta, seed, steps=30, vertex_w=seed % 3 == 0)
        assert worst <= 1e-6, seed


def test_nan_state_mid_run_takes_the_backup_and_learns_on(toy):
    """A NaN measurement in the middle of a run: that step applies the backup with
    ``"non_finite_state"`` (no exception, the model is not falsified), and the estimator
    resumes from the next two finite states — a transition across the NaN is never used."""
    ctrl = RAPSF(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, toy.Theta0,
                 estimator=BoxUpdate(toy.sys, toy.W, toy.Theta0))
    theta_star = toy.Theta0.vertices().mean(axis=0)
    A, B = model_matrices(toy.sys, theta_star)
    x = np.array([0.5, 0.1])
    for k in range(8):
        meas = np.array([np.nan, x[1]]) if k == 3 else x
        u, info = ctrl.step(meas, np.array([1.0]))
        if k == 3:
            assert info.status == "non_finite_state" and info.fallback == "backup"
        else:
            assert info.status != "model_falsified", (k, info.status)
        assert np.all(np.isfinite(u)) and not ctrl.falsified
        assert ctrl.Theta.contains(theta_star, tol=1e-7)
        x = A @ x + B @ u


def test_an_empty_set_error_inside_a_set_estimator_is_not_a_falsification(toy, monkeypatch):
    """A :class:`SetEstimator` certifies "empty" and records ``falsified``; an
    :class:`EmptySetError` escaping it (a set it builds, an uncertified LP verdict) keeps
    Θ_{k−1} with ``theta_update_failed`` instead of running the backup for the rest of the run
    (review, session 10). A plain estimator that raises keeps the documented contract."""
    est = BoxUpdate(toy.sys, toy.W, toy.Theta0)

    def raising(*args, **kwargs):
        raise EmptySetError("a set built inside the update is empty")

    monkeypatch.setattr(est, "update", raising)
    ctrl = RAPSF(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, toy.Theta0, estimator=est)
    ctrl.step(np.array([0.5, 0.1]), np.array([1.0]))
    u, info = ctrl.step(np.array([0.5, 0.1]), np.array([1.0]))
    assert info.status == "theta_update_failed" and not ctrl.falsified
    assert info.fallback is None and ctrl.Theta is toy.Theta0

    class _Raising:
        def update(self, xp, up, x):
            raise EmptySetError("no θ explains the data")

    ctrl = RAPSF(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, toy.Theta0,
                 estimator=_Raising())
    ctrl.step(np.array([0.5, 0.1]), np.array([1.0]))
    u, info = ctrl.step(np.array([0.5, 0.1]), np.array([1.0]))
    assert info.status == "model_falsified" and ctrl.falsified
