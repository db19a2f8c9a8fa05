"""§8.2 lane change: the incremental RPI design of :mod:`balustrade.design.incremental_rpi`
holds for the nonlinear bicycle (sampled and worst-case NLP checks of E and of the terminal
set) while the linearization design fails them (negative control); the Jacobian bound
contains every Jacobian; the robust PCBF's h_r does not increase along a closed loop; the
quick reproduction's metrics are consistent (slow)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from balustrade.design.incremental_rpi import (
    PolytopicLDI,
    sampled_rpi_check,
    sampled_terminal_check,
    worst_case_rpi_check,
    worst_case_terminal_check,
)
from balustrade.dsl.sets import Box
from balustrade.errors import BalustradeError
from balustrade.examples.bicycle import bicycle_design, bicycle_ldi
from balustrade.models.bicycle import bicycle, bicycle_sets, input_matrix, jacobian_ldi


@pytest.fixture(scope="module")
def new():
    return bicycle_design()


@pytest.fixture(scope="module")
def old():
    return bicycle_design(method="linearization")


def test_jacobian_bound_contains_every_jacobian():
    """∂f/∂x = A0 + Σ a_k E_k with a_k in the computed intervals at random states of a
    box wider than X, and ∂f/∂u = B; the vertices' hull is what the SDP covers."""
    X, _, _ = bicycle_sets()
    lo, hi = X.lb - [0, 0.1, 0.0, 0.1], X.ub + [0, 0.1, 0.0, 0.1]
    A0, dirs, intervals = jacobian_ldi(lo, hi)
    system, rng = bicycle(), np.random.default_rng(1)
    box = Box(lo, hi)
    for x in box.sample(500, rng):
        A, B = system.jacobians(x, rng.standard_normal(2))
        a = np.array([A[0, 1], A[0, 2], A[1, 2], A[1, 3]])
        assert np.allclose(A, A0 + sum(ak * E for ak, E in zip(a, dirs)))
        assert np.all(a >= intervals[:, 0] - 1e-12) and np.all(a <= intervals[:, 1] + 1e-12)
        assert np.allclose(B, input_matrix())
    # the interval ends are attained (tight bound): corners of the box
    assert np.isclose(intervals[3, 1], 0.05 / 0.09 * hi[2] / np.cos(hi[3]) ** 2)
    ldi = PolytopicLDI(A0, tuple(dirs), intervals, input_matrix(), box)
    assert len(ldi.vertices()) == 16


def test_bad_inputs_name_the_argument():
    X, _, _ = bicycle_sets()
    with pytest.raises(BalustradeError, match="psi range"):
        jacobian_ldi(X.lb - [0, 1.2, 0, 0], X.ub)
    with pytest.raises(BalustradeError, match="method"):
        bicycle_design(method="linearisation")
    with pytest.raises(BalustradeError, match="intervals"):
        PolytopicLDI(np.eye(4), (np.eye(4),), np.array([[1.0, 0.0]]), input_matrix(),
                     Box(X.lb, X.ub))


def test_domain_covers_X_plus_E(new):
    """The Jacobian domain D contains X ⊕ (semi-axes of E) along ψ, v, δ: every nominal
    z ∈ X and true x = z + e lie in D, where Claim 1 holds."""
    info = new.error.info
    assert info["domain_covers_X_plus_E"]
    axes = np.sqrt(np.diag(np.linalg.inv(new.error.E.P)))
    lb, ub = np.array(info["domain"]["lb"]), np.array(info["domain"]["ub"])
    assert np.all(lb[1:] <= new.X.lb[1:] - axes[1:] + 1e-9)
    assert np.all(ub[1:] >= new.X.ub[1:] + axes[1:] - 1e-9)
    assert np.isinf(lb[0]) and np.isinf(ub[0])     # any p_y


def test_incremental_design_passes_both_rpi_checks(new):
    d = new
    s = sampled_rpi_check(d.system, d.error, d.X, d.U_E, d.W, samples=4000, seed=3)
    assert s.ok and s.margin < -0.01, s.summary()
    w = worst_case_rpi_check(d.system, d.error, d.X, d.U_E, d.W, starts=4, seed=3)
    assert w.ok and w.margin < 0, w.summary()
    assert w.margin >= s.margin - 1e-9            # the NLP starts from sampled worst points


def test_linearization_design_fails_both_rpi_checks(old):
    """Negative control: the linearization E is not RPI for the nonlinear model."""
    d = old
    s = sampled_rpi_check(d.system, d.error, d.X, d.U_E, d.W, samples=4000, seed=3)
    assert not s.ok and s.margin > 0.1, s.summary()
    w = worst_case_rpi_check(d.system, d.error, d.X, d.U_E, d.W, starts=4, seed=3)
    assert not w.ok and w.margin >= s.margin - 1e-9, w.summary()


def test_terminal_set_invariant_for_the_nonlinear_model(new, old):
    for check in (lambda d: sampled_terminal_check(d.system, d.terminal_spec(), 4000, 2),
                  lambda d: worst_case_terminal_check(d.system, d.terminal_spec(), 4, 2)):
        good, bad = check(new), check(old)
        assert good.ok and good.parts["h_f(z+)"] < -0.05, good.summary()
        assert good.parts["input_rows"] < 0 and good.parts["state_rows"] <= 1e-7
        assert not bad.ok and bad.parts["h_f(z+)"] > 0.01, bad.summary()


def test_the_rpi_check_sees_a_shrunk_set(new):
    """The check can fail: the same K with E shrunk to half is not RPI (the disturbance
    alone leaves it)."""
    from dataclasses import replace

    d = new
    small = replace(d.error, E=d.error.E.scale(0.5))
    s = sampled_rpi_check(d.system, small, d.X, d.U_E, d.W, samples=2000, seed=0)
    assert not s.ok


def test_robust_pcbf_h_r_non_increasing_from_the_adjacent_lane(new):
    from balustrade.control.robust import RobustPCBFSafetyFilter
    from balustrade.reproduce.lane_change import TARGET, closed_loop, disturbances, run_metrics

    d = new
    robust = RobustPCBFSafetyFilter.build(d.system, d.X, d.U, d.cbf, d.cbf.policy, d.N,
                                          d.deltas, d.error, d.alpha_f, target=TARGET,
                                          slack_target=TARGET)
    r = closed_loop(robust, d, disturbances(d, 0, 30))
    m = run_metrics(r, d, "h_r")
    assert r["h_r"][0] > 1.0                       # starts outside X: h_r > 0
    assert m["non_increasing"] and m["nan_values"] == 0, m
    assert m["entered_S_r_at"] >= 0 and m["X_kept_after_S_r"], m
    assert abs(m["final_p_y"]) <= 0.2


@pytest.mark.slow
def test_quick_reproduction(tmp_path):
    from balustrade.reproduce import run

    m = run("lane-change", tmp_path, quick=True)
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["must_show"] == json.loads(json.dumps(m["must_show"]))
    ms = m["must_show"]
    assert ms["rpi_checks_pass"]
    assert ms["h_r_non_increasing_every_robust_run"]
    assert ms["h_tilde_non_increasing_every_multiobjective_run"]
    assert ms["X_kept_once_in_S_r_every_run"]
    assert m["c_runs"]["robust"]["runs"] == 5
    # session 11: the default configuration (ρ = 0.5, Δ_i = i·1e-3) is recorded and both
    # algorithms converge on the 5 seeds, the multiobjective one the gentler
    assert saved["config"]["name"] == "converging" and saved["rho"] == 0.5
    assert saved["delta_step"] == pytest.approx(1e-3)
    assert ms["both_converge_every_run"] and ms["mo_peak_lat_acc_le_robust_every_seed"]
    for name in ("robust", "multiobjective"):
        assert m["python_seed0"][name]["fallbacks"] == 0
    assert (tmp_path / "fig8_1_lane_change.png").is_file()


def test_bicycle_ldi_pad_widens_the_intervals():
    a, b = bicycle_ldi(), bicycle_ldi(np.array([0.1, 0.0, 0.1]))
    assert np.all(b.intervals[:, 0] <= a.intervals[:, 0])
    assert np.all(b.intervals[:, 1] >= a.intervals[:, 1])
    assert b.intervals[3, 1] > a.intervals[3, 1]


def test_design_arguments_are_checked():
    """Claim 2 needs λ_f ∈ (0, 1]; shapes and non-finite numbers name the argument."""
    from balustrade.design.incremental_rpi import incremental_rpi, robust_terminal_cbf
    from balustrade.errors import BalustradeError
    from balustrade.examples.bicycle import bicycle_ldi
    from balustrade.models.bicycle import bicycle_sets

    ldi = bicycle_ldi()
    X, U, W = bicycle_sets()
    x_s = np.array([0.0, 0.0, 1.1, 0.0])
    with pytest.raises(BalustradeError, match="decrease_factor"):
        robust_terminal_cbf(ldi, X, U, x_s, decrease_factor=1.5)
    with pytest.raises(BalustradeError, match="delta_N"):
        robust_terminal_cbf(ldi, X, U, x_s, delta_N=float("nan"))
    with pytest.raises(BalustradeError, match="x_s"):
        robust_terminal_cbf(ldi, X, U, x_s[:3])
    with pytest.raises(BalustradeError, match="x_s"):
        incremental_rpi(ldi, W, X, U, np.array([[0.0], [1.0], [0.0], [0.0]]), x_s[:3])


def test_seeded_runs_resume_from_saved_seeds(new, tmp_path, monkeypatch):
    """The seeded runs of the reproduction are resumable: each seed is saved when done and
    read back (not run again) for the same emitted controllers; other controllers (another
    source hash) run again."""
    from balustrade.control.robust import RobustPCBFSafetyFilter
    from balustrade.reproduce import lane_change as L

    monkeypatch.setattr(L, "STEPS", 3)
    d = new
    ctrl = RobustPCBFSafetyFilter.build(d.system, d.X, d.U, d.cbf, d.cbf.policy, d.N,
                                        d.deltas, d.error, d.alpha_f, target=L.TARGET,
                                        slack_target=L.TARGET)
    ctrl.accelerated = {"hash": "a" * 40}        # as accelerate() sets it
    rows = L.seeded_runs({"robust": ctrl}, d, [0, 1], tmp_path, log=False)
    assert [r["seed"] for r in rows] == [0, 1]
    assert L.seed_file(tmp_path, 1).is_file() and len(rows[1]["robust"]["times"]) == 3

    class Stale:
        """A controller that must not run (its seeds are saved)."""

        def __init__(self, digest: str):
            self.accelerated = {"hash": digest}

        def reset(self):
            raise AssertionError("ran a saved seed again")

    again = L.seeded_runs({"robust": Stale("a" * 40)}, d, [0, 1], tmp_path, log=False)
    assert again == json.loads(json.dumps(rows, default=L._json))
    with pytest.raises(AssertionError, match="ran a saved seed again"):
        L.seeded_runs({"robust": Stale("b" * 40)}, d, [1], tmp_path, log=False)


@pytest.mark.slow
def test_algorithm_6_4_reaches_S_r_at_rho_0_not_at_0_9(new):
    """Session 10 ρ sweep (docs/vehicles.md): seed 0, 200 steps, Python. ρ = 0 (the whole
    candidate decrease) reaches S_r and the lane edge; ρ = 0.9 (SPEC default) does not,
    with (6.15g) active at every step; every step ok."""
    from balustrade.reproduce.lane_change import rho_sweep

    rows = {r["rho"]: r for r in rho_sweep(new, rhos=(0.0, 0.9), seeds=(0,))}
    assert rows[0.0]["converged"] and 0 <= rows[0.0]["entered_S_r_at"] < 200
    assert not rows[0.9]["converged"] and rows[0.9]["entered_S_r_at"] == -1
    assert rows[0.9]["decrease_bound_active_steps"] == 200
    assert rows[0.0]["not_ok"] == rows[0.9]["not_ok"] == 0
    # session 11 (docs/vehicles.md): (6.15g) passes on exactly 1 − ρ of the candidate's
    # decrease, which is ≈ 13 % of h̃ (mostly ‖ξ*_0‖): h̃ falls ≈ 1.3 % per step and the
    # car is still outside the lane after 200 steps
    assert rows[0.9]["decrease_realized_over_candidate"] == pytest.approx(0.1, abs=1e-3)
    assert 0.10 <= rows[0.9]["decrease_candidate_share"] <= 0.16
    assert rows[0.9]["first_step_in_lane"] == -1 and rows[0.9]["delta_step"] == 1e-4


def test_decrease_rates_split_candidate_and_realized_decrease():
    """:func:`decrease_rates` on a made-up Algorithm 6.4 trace: the candidate offers 13 % of
    h̃ per step and (6.15g) with ρ = 0.9 passes on a tenth of it; steps at h̃ = 0 and a
    run without candidate values (Algorithm 5.2) are left out."""
    from balustrade.reproduce.lane_change import _holds_from, decrease_rates

    ht, hc = [2.0], [2.0]
    for _ in range(30):
        cand = ht[-1] * (1 - 0.13)
        hc.append(cand)
        ht.append(0.1 * cand + 0.9 * ht[-1])
    ht += [0.0, 0.0]
    hc += [0.0, 0.0]
    rates = decrease_rates({"h_tilde": np.array(ht), "h_cand": np.array(hc)})
    assert rates["candidate_share"] == pytest.approx(0.13)
    assert rates["realized_over_candidate"] == pytest.approx(0.1)
    none = decrease_rates({"h_tilde": np.array(ht), "h_cand": np.full(len(ht), np.nan)})
    assert none == {"candidate_share": None, "realized_over_candidate": None}
    assert [_holds_from(np.array(m, bool)) for m in ([0, 1, 0, 1, 1], [1, 1], [1, 0], [])] \
        == [3, 0, -1, -1]


def test_rho_sweep_cli_passes_its_options(tmp_path):
    """``--rho-sweep --rhos --delta-step --steps --record-h-r`` reach :func:`rho_sweep`."""
    from balustrade.reproduce.lane_change import main

    assert main(["--rho-sweep", "--rhos", "0.5", "--delta-step", "2e-4", "--steps", "2",
                 "--seeds", "1", "--first", "3", "--record-h-r", "--out", str(tmp_path)]) == 0
    (row,) = json.loads((tmp_path / "rho_sweep.json").read_text())
    assert (row["rho"], row["seed"], row["steps"]) == (0.5, 3, 2)
    assert row["delta_step"] == pytest.approx(2e-4)
    assert row["h_r_zero_at"] == -1 and row["final_h_r"] > 0      # 2 steps: still outside
    with pytest.raises(SystemExit):
        main(["--rho-sweep", "--rhos", "a,b", "--out", str(tmp_path)])


@pytest.mark.parametrize("args, name", [
    (["--steps", "0"], "--steps"), (["--steps", "-3"], "--steps"),
    (["--seeds", "0"], "--seeds"), (["--jobs", "0"], "--jobs"), (["--first", "-1"], "--first"),
    (["--delta-step", "0"], "--delta-step"), (["--rhos", ","], "--rhos")])
def test_rho_sweep_cli_rejects_non_positive_counts(tmp_path, capsys, args, name):
    """``--rho-sweep --steps 0`` ended in an IndexError (an empty closed loop); now every
    count of the CLI is checked when parsed, with an error naming the argument."""
    from balustrade.reproduce.lane_change import main

    with pytest.raises(SystemExit) as exc:
        main(["--rho-sweep", "--rhos", "0.5", *args, "--out", str(tmp_path)])
    assert exc.value.code == 2 and name in capsys.readouterr().err
    assert not (tmp_path / "rho_sweep.json").exists()


@pytest.mark.slow
def test_algorithm_6_4_reaches_S_r_at_rho_0_5_with_larger_delta_steps():
    """Session 11 (docs/vehicles.md): with Δ_i = i·1e-3 (the thesis' Δ of §6.5) instead of
    SPEC's i·1e-4 for the lane change, ρ = 0.5 reaches the lane and h̃ = 0 within 200
    steps on seed 0; with i·1e-4 it does not (the ρ sweep)."""
    from balustrade.reproduce.lane_change import rho_sweep

    (row,) = rho_sweep(bicycle_design(delta_step=1e-3), rhos=(0.5,), seeds=(0,))
    assert row["converged"] and 0 <= row["entered_S_r_at"] < 150, row
    assert 0 <= row["first_step_in_lane"] < 80 and row["not_ok"] == 0, row


def test_configs_are_wired(tmp_path):
    """Session 11: the two configurations of the lane change are defined in one place and
    reach the design, the controllers, the metrics header and the ρ-sweep CLI; the default
    is ``converging`` (ρ = 0.5, Δ_i = i·1e-3), ``spec`` keeps SPEC §3.6's ρ = 0.9, i·1e-4."""
    from balustrade.reproduce import lane_change as L

    assert L.DEFAULT_CONFIG == "converging"
    conv, spec = L.config("converging"), L.config("spec")
    assert (conv.rho, conv.delta_step) == (0.5, 1e-3)
    assert (spec.rho, spec.delta_step) == (0.9, 1e-4) and L.RHO == 0.9
    with pytest.raises(BalustradeError, match="config"):
        L.config("thesis")
    for cfg in (conv, spec):
        d = L.design(cfg)
        assert np.allclose(d.deltas, cfg.delta_step * np.arange(d.N))
        ctrls = L.controllers(d, rho=cfg.rho)
        assert ctrls["multiobjective"].rho == cfg.rho
        assert np.allclose(ctrls["robust"].deltas, d.deltas)
        head = json.loads(json.dumps(L.header(cfg, d, 5), default=L._json))
        assert head["config"]["name"] == cfg.name and head["rho"] == cfg.rho
        assert head["delta_step"] == pytest.approx(cfg.delta_step)
    # the CLI: --config sets the sweep's Δ step (unless --delta-step is given)
    for name, step in (("converging", 1e-3), ("spec", 1e-4)):
        out = tmp_path / name
        assert L.main(["--rho-sweep", "--config", name, "--rhos", "0.5", "--steps", "1",
                       "--seeds", "1", "--out", str(out)]) == 0
        (row,) = json.loads((out / "rho_sweep.json").read_text())
        assert row["delta_step"] == pytest.approx(step)
    with pytest.raises(SystemExit):
        L.main(["--config", "thesis", "--out", str(tmp_path)])


def test_controllers_default_rho_is_the_designs_configuration():
    """Audit D, session 15: ``controllers(d)`` without ``rho`` gave ρ = 0.9 (SPEC) for every
    design, so the default ``converging`` design (Δ step 1e-3, ρ = 0.5) silently ran
    Algorithm 6.4 at a ρ of another configuration. The default now follows the design."""
    from balustrade.reproduce import lane_change as L

    for cfg in (L.config("converging"), L.config("spec")):
        d = L.design(cfg)
        assert L.controllers(d)["multiobjective"].rho == cfg.rho
        assert L.config_of(d).name == cfg.name
    assert L.controllers(L.design(L.config("spec")), rho=0.3)["multiobjective"].rho == 0.3
