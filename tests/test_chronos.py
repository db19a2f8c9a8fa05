"""The Chronos race car of §8.4 (SPEC §2.33): track, model, terminal CBF design."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from balustrade.errors import BalustradeError, ShapeError
from balustrade.models.chronos import (
    TABLE_8_1,
    ChronosParams,
    cartesian_ode,
    chronos_cartesian,
    chronos_frenet,
    chronos_plant,
    chronos_sets,
    constraint_values,
    corner_offsets,
    steady_speed,
)
from balustrade.models.track import Track, oval, plot_track


# -- track ----------------------------------------------------------------------------------
def test_oval_curvature_closes_the_loop():
    tr = oval()
    c = tr.closure()
    assert c["turning"] == pytest.approx(2 * np.pi, abs=1e-7)
    assert c["gap"] < 1e-6
    assert tr.is_closed()
    assert tr.length == pytest.approx(4.0 + 2 * np.pi * 0.6)
    # the smoothed curvature is continuous and keeps the arcs' curvature in their middle
    s = np.linspace(0.0, tr.length, 20001)
    k = tr.curvature(s)
    assert np.max(np.abs(np.diff(k))) < 1e-2
    assert tr.curvature(2.0 + 0.3 * np.pi) == pytest.approx(1 / 0.6)
    assert tr.curvature(1.0) == 0.0
    # ramps are centred on the junctions (clothoids): half the jump at the junction itself
    assert tr.curvature(2.0) == pytest.approx(0.5 / 0.6)
    assert tr.curvature(0.0) == pytest.approx(0.5 / 0.6)


def test_open_track_is_reported_not_closed():
    tr = Track([2.0, np.pi * 0.6, 2.0, np.pi * 0.5], [0.0, 1 / 0.6, 0.0, 1 / 0.6])
    assert not tr.is_closed()
    assert abs(tr.closure()["heading_error"]) > 0.1


def test_symbolic_curvature_matches_numeric_and_is_periodic():
    tr = oval()
    s = ca.SX.sym("s")
    f = ca.Function("k", [s], [tr.kappa(s)])
    ss = np.linspace(-3.0, 3 * tr.length, 1501)
    np.testing.assert_allclose(np.asarray(f(ss)).ravel(), tr.curvature(ss), atol=1e-12)
    np.testing.assert_allclose(tr.curvature(ss), tr.curvature(ss + tr.length), atol=1e-12)


def test_frenet_cartesian_round_trip():
    tr = oval()
    rng = np.random.default_rng(0)
    s = rng.uniform(0, tr.length, 500)
    n = rng.uniform(-0.3, 0.3, 500)
    mu = rng.uniform(-1.0, 1.0, 500)
    S, N, M = tr.to_frenet(*tr.to_cartesian(s, n, mu))
    np.testing.assert_allclose(S, s, atol=1e-8)
    np.testing.assert_allclose(N, n, atol=1e-8)
    np.testing.assert_allclose(M, mu, atol=1e-8)


def test_plot_track_draws(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tr = oval()
    x, y, _ = tr.to_cartesian(np.linspace(0, 5, 50), np.zeros(50), np.zeros(50))
    fig, ax = plt.subplots()
    lc = plot_track(ax, tr, [np.column_stack([x, y])], color_by=[np.linspace(0, 1, 50)],
                    markers=np.array([[x[3], y[3]]]))
    assert lc is not None
    with pytest.raises(ShapeError, match="color_by"):
        plot_track(ax, tr, [np.column_stack([x, y])], color_by=[np.ones(3)])
    plt.close(fig)


def test_track_bad_input():
    with pytest.raises(ShapeError, match="curvatures"):
        Track([1.0, 2.0], [0.0])
    with pytest.raises(BalustradeError, match="lengths"):
        Track([1.0, -2.0], [0.0, 1.0])
    with pytest.raises(BalustradeError, match="transition"):
        Track([1.0, 0.1], [0.0, 1.0], transition=0.2)
    with pytest.raises(BalustradeError, match="width"):
        oval(width=-1.0)


# -- model ----------------------------------------------------------------------------------
def test_sanity_positive_steer_turns_left():
    """SPEC §2.33: δ > 0, v_y = ω = 0 ⇒ ω̇ > 0 (and the lateral force pushes left)."""
    f = cartesian_ode()
    for vx in (0.05, 0.5, 1.0, 2.0):
        xdot = np.asarray(f(ca.DM([0, 0, 0, vx, 0, 0]), ca.DM([0.3, 0.2]))).ravel()
        assert xdot[5] > 0
        assert xdot[4] > 0
    xdot = np.asarray(f(ca.DM([0, 0, 0, 1.0, 0, 0]), ca.DM([0.3, -0.2]))).ravel()
    assert xdot[5] < 0


def test_guards_finite_at_standstill_and_c5_only_when_moving():
    f = cartesian_ode()
    xdot = np.asarray(f(ca.DM([0, 0, 0, 0.0, 0.01, 0.1]), ca.DM([0.0, 0.3]))).ravel()
    assert np.all(np.isfinite(xdot))
    # standing still with T = 0: no drag, no c5 -> no backwards acceleration
    xdot = np.asarray(f(ca.DM.zeros(6), ca.DM([0.0, 0.0]))).ravel()
    assert xdot[3] == 0.0
    assert steady_speed(0.3) == pytest.approx(1.441, abs=1e-3)


def test_frenet_and_cartesian_simulations_agree():
    """The same inputs applied to the Cartesian and the Frenet RK4 models give the same
    trajectory once mapped through the track (P-controlled, ~1.5 laps of the oval)."""
    tr = oval()
    P, C = chronos_plant(tr), chronos_cartesian()
    xf = np.array([0.3, 0.05, 0.1, 0.8, 0.0, 0.0])
    px, py, psi = tr.to_cartesian(xf[0], xf[1], xf[2])
    xc = np.array([px, py, psi, *xf[3:]])
    worst = 0.0
    for _ in range(400):
        u = np.array([0.3, np.clip(-1.0 * (xf[1] + 0.3 * np.sin(xf[2])), -0.4, 0.4)])
        xf, xc = P.step(xf, u), C.step(xc, u)
        s, n, mu = tr.to_frenet(xc[0], xc[1], xc[2])
        ds = (s[0] - xf[0] + tr.length / 2) % tr.length - tr.length / 2
        worst = max(worst, abs(ds), abs(n[0] - xf[1]),
                    abs(np.angle(np.exp(1j * (mu[0] - xf[2])))),
                    float(np.max(np.abs(xc[3:] - xf[3:]))))
    assert xf[0] > tr.length  # it went round
    assert worst < 1e-5


def test_constraints_and_corners():
    X, U = chronos_sets()
    p = TABLE_8_1
    x = np.array([1.0, 0.0, 0.0, 1.0, 0.0, 0.0])
    lf, rf = corner_offsets(x)
    assert lf == pytest.approx(p.w_veh / 2) and rf == pytest.approx(-p.w_veh / 2)
    assert X.contains(x)
    edge = 0.25 - p.w_veh / 2
    assert X.contains(np.r_[1.0, edge - 1e-6, 0, 1, 0, 0])
    assert not X.contains(np.r_[1.0, edge + 1e-3, 0, 1, 0, 0])
    assert not X.contains(np.r_[1.0, 0.0, 1.6, 1, 0, 0])
    np.testing.assert_allclose(U.lb, [0.0, -0.4])
    np.testing.assert_allclose(U.ub, [1.0, 0.4])
    sym = np.asarray(ca.Function("c", [s := ca.SX.sym("x", 6)], [constraint_values(s)])(x))
    np.testing.assert_allclose(sym.ravel(), constraint_values(x))


def test_model_bad_input():
    with pytest.raises(BalustradeError, match="m"):
        ChronosParams(m=-1.0)
    with pytest.raises(BalustradeError, match="track"):
        chronos_frenet(track="oval")
    with pytest.raises(ShapeError):
        chronos_frenet().step(np.zeros(5), np.zeros(2))
    with pytest.raises(BalustradeError, match="steps"):
        chronos_cartesian(steps=0)
    with pytest.raises(BalustradeError, match="T"):
        steady_speed(1.5)


# -- PCBF design (examples/chronos.py) ---------------------------------------------------------
@pytest.fixture(scope="module")
def cbf():
    from balustrade.examples.chronos import chronos_terminal_cbf

    return chronos_terminal_cbf()


def test_steady_states_are_equilibria_of_the_frenet_model(cbf):
    ss = cbf.steady
    assert ss.kappa.size == 21
    assert ss.kappa[0] == pytest.approx(0.0) and ss.kappa[-1] == pytest.approx(1 / 0.6)
    np.testing.assert_allclose(ss.z[0], [0, 0, 1, 0, 0], atol=1e-9)
    # at the arcs' curvature the car yaws at ω = κ·ṡ and steers left
    assert ss.z[-1][4] == pytest.approx(ss.kappa[-1] * (np.cos(ss.z[-1][1]) - ss.z[-1][3]
                                                        * np.sin(ss.z[-1][1])), rel=1e-6)
    assert ss.u[-1][1] > 0.1
    # the cubic fits reproduce the 21 steady states used by h_f and pi_f
    s_arc = 2.0 + 0.3 * np.pi
    x = np.r_[s_arc, ss.z[-1]]
    assert cbf.V(x) < 1e-8
    np.testing.assert_allclose(cbf.policy(x), ss.u[-1], atol=1e-4)  # cubic fit: ~5e-6


def test_terminal_cbf_invariance_check(cbf):
    from dataclasses import replace

    from balustrade.examples.chronos import check_invariance

    rep = check_invariance(cbf, starts=3, seed=5)
    assert rep.failed == 0 and rep.solved == 3 * 11
    assert rep.ok, rep
    # the check finds a counterexample when the ellipsoid is too large
    big = replace(cbf, P=cbf.P / 4.0)
    bad = check_invariance(big, starts=3, seed=5)
    assert bad.constraints > 0 and not bad.ok


def test_pcbf_on_and_off_the_track():
    from balustrade.backends import compile
    from balustrade.examples.chronos import chronos_design
    from balustrade.problems.pcbf import pcbf_slack_problem

    d = chronos_design(N=20)
    assert d.N == 20 and d.deltas[3] == pytest.approx(3e-4) and d.alpha_f == 10.0
    prob = compile(pcbf_slack_problem(d.system, d.X, d.U, d.cbf, d.N, d.deltas,
                                      alpha_f=d.alpha_f, slack_norm=1), "exact")
    on = prob.solve({"x0": np.array([0.5, 0.0, 0.0, 1.0, 0.0, 0.0])})
    assert on.success and on.objective <= 1e-6
    off = prob.solve({"x0": np.array([0.5, 0.3, 0.0, 1.0, 0.0, 0.0])})
    assert off.success and off.objective > 0.05  # starts outside X: xi_0 >= 0.086


def test_chronos_is_a_sampling_problem():
    from balustrade.learn.sampler import PROBLEMS

    assert PROBLEMS["chronos"] == "balustrade.examples.chronos:chronos_problems"


def test_oval_straights_are_axis_aligned():
    tr = oval()
    _, _, psi = tr.centre(np.array([0.5, 1.0, 1.5]))
    np.testing.assert_allclose(psi, 0.0, atol=1e-7)
    _, _, psi = tr.centre(np.array([2.0 + np.pi * 0.6 + 1.0]))
    np.testing.assert_allclose(psi, np.pi, atol=1e-7)


# -- reproduction --------------------------------------------------------------------------------
def test_scenario_one_leaves_the_track_without_filter():
    from balustrade.reproduce import registry
    from balustrade.reproduce.chronos import SCENARIOS, closed_loop, violation_sites

    assert "chronos" in registry()
    run = closed_loop(oval(), SCENARIOS["p-controller"], max_steps=150)
    sites = violation_sites(run)
    assert sites and 2.0 < sites[0]["s"] < 3.0  # at the entry of the first curve
    assert run["c_max"].max() > 0.01
    # the controller alone on a straight stays inside
    assert run["c_max"][:50].max() < 0


def test_grid_filter_has_the_thesis_grid_and_a_periodic_h():
    from balustrade.learn.train import MLPModel
    from balustrade.reproduce.chronos import grid_filter, h_function

    rng = np.random.default_rng(0)
    widths = [6, 32, 32, 32, 32, 1]
    model = MLPModel([rng.standard_normal((o, i)) * 0.3 for i, o in zip(widths, widths[1:])],
                     [rng.standard_normal(o) * 0.1 for o in widths[1:]], np.zeros(6),
                     np.ones(6), output_transform="cbrt")
    tr = oval()
    h = h_function(model, tr)
    x = np.array([1.3, 0.1, -0.2, 1.2, 0.05, 0.3])
    assert float(h(x)) == pytest.approx(float(model(x[None])[0]), rel=1e-9)
    assert float(h(x + np.r_[tr.length, 0, 0, 0, 0, 0])) == pytest.approx(float(h(x)),
                                                                           rel=1e-9)
    flt = grid_filter(h, tr)
    assert flt.rho == 0.9
    assert len(flt.offsets) == 11 * 5  # ΔT = 0.1 within ±0.5, Δδ = 0.05 within ±0.1
    assert np.max(np.abs(flt.offsets), axis=0) == pytest.approx([0.5, 0.1])
    u, info = flt.step(x, np.array([0.3, 0.0]))
    assert np.all(np.abs(u - np.array([0.3, 0.0])) <= [0.5 + 1e-12, 0.1 + 1e-12])
    assert 0.0 <= u[0] <= 1.0 and abs(u[1]) <= 0.4
