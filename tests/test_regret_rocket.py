"""Rocket example of Section 3.8 (issue 4): quick pipeline by default, the T = 25 run is slow."""

from pathlib import Path

import numpy as np
import pytest

from balustrade.models.rocket import RocketRegretSetup
from balustrade.reproduce import registry
from balustrade.reproduce.rocket_regret import (
    CONTROLLERS,
    PROFILES,
    deterministic_profiles,
    random_profiles,
    run,
)


def test_rocket_model_matches_the_issue():
    s = RocketRegretSetup()
    assert s.A[0, 2] == s.A[1, 3] == s.A[4, 5] == pytest.approx(0.1)
    assert s.B[2, 0] == s.B[3, 1] == s.B[5, 0] == pytest.approx(0.1)
    # the ellipsoid passes through the vertices of the box
    assert s.box @ s.P @ s.box == pytest.approx(1.0)
    assert s.omega == pytest.approx(25 / np.min(np.diag(s.P)))
    Au, bu = s.input_halfspaces()
    hover = np.zeros(2)
    assert np.all(Au @ hover <= bu)
    assert not np.all(Au @ np.array([0.0, -0.6 * 9.81]) <= bu)   # below -0.5 mg


def test_profiles_lie_in_the_pointwise_set():
    s = RocketRegretSetup(T=25)
    prof = deterministic_profiles(25, s.box)
    prof.update(random_profiles(25, s.P, 5, seed=1))
    for name, w in prof.items():
        w = w.reshape(-1, 6)
        assert np.all(np.einsum("ti,ij,tj->t", w, s.P, w) <= 1 + 1e-12), name
    assert np.allclose(prof["stair"][9:17], 0.0) and np.allclose(prof["stair"][:9], -s.box)
    assert np.allclose(prof["step"][:13], 0.0) and np.allclose(prof["step"][13:], s.box)


def _check_metrics(m: dict) -> None:
    # "optimal_inaccurate" (Clarabel stalled within 10x of its tolerances, seen for the 𝒪-weighted
    # SDPs at T = 25) is accepted because the levels are certified below, without the solver
    assert all(st in ("optimal", "optimal_inaccurate") for st in m["status"].values()), m["status"]
    # every synthesis is ok (optimal and certified), except a banded one that could not be
    # re-solved outside banded coordinates (SCRW at T = 25: its dense cone is too large), and
    # that must be said in the metrics
    for name, ok in m["ok"].items():
        retry = m["banded_fallback"][name] or {}
        assert ok or (retry.get("status") == "failed"
                      and retry.get("message", "").startswith("too large")), (name, m["status"])
    cert = m["certificates"]
    assert set(cert) == {"SDR", "SCR", "SDRW", "SCRW"}
    for name in ("SDR", "SCR"):       # energy bounds: the S-procedure is lossless, level exact
        # to the solver's accuracy: its gap tolerance (1e-8), or for "optimal_inaccurate" the
        # reduced one it then met (Clarabel's reduced_tol_gap_rel = 5e-5; the 𝒪-weighted SCR at
        # T = 25 lands 1.4e-5 above its controller's exact level)
        rel = 1e-5 if m["status"][name] == "optimal" else 5e-5
        assert cert[name]["exact"] == pytest.approx(cert[name]["sdp"], rel=rel), name
    for name in ("SDRW", "SCRW"):     # pointwise: a certified lower bound under the SDP level
        assert cert[name]["lower_bound"] <= cert[name]["sdp"] * (1 + 1e-6), name
        assert cert[name]["lower_bound"] >= 2 / np.pi * cert[name]["sdp"] * 0.5, name
    assert m["constraints_satisfied"] and m["closed_loop_runs"] > 0
    norm = m["normalized_cost"]
    for prof in PROFILES:
        assert min(norm[prof].values()) == pytest.approx(1.0)
        assert set(norm[prof]) == set(CONTROLLERS)
    lv = m["levels"]
    # Proposition 3.10: the pointwise-bound levels are never above the energy-bound ones
    assert lv["SDRW"] <= lv["SDR"] * (1 + 1e-6)
    assert lv["SCRW"] <= lv["SCR"] * (1 + 1e-6)
    # thesis pattern (SPEC 3.1 SOFT): SH∞ worst everywhere, SH2 best on the random profiles
    for prof in PROFILES:
        assert norm[prof]["SH∞"] == max(norm[prof].values())
    for prof in ("N_W", "U_W"):
        assert norm[prof]["SH2"] == pytest.approx(1.0)
    assert "summary_table" in m and "SDRW" in m["summary_table"]


def test_rocket_quick_reproduction(tmp_path: Path):
    assert registry()["rocket-regret"] is run
    m = run(tmp_path, quick=True)
    _check_metrics(m)
    assert (tmp_path / "metrics.json").exists()
    assert all(Path(p).exists() for p in m["plots"])


@pytest.mark.slow
def test_rocket_full_reproduction(tmp_path: Path):
    m = run(tmp_path, quick=False)
    _check_metrics(m)
    assert m["T"] == 25 and m["draws"] == 100
    # relative reductions of the level are of the order of tens of percent (thesis 47 %, 25 %)
    red = m["level_reduction_percent"]
    assert red["SDR->SDRW"] > 10 and red["SCR->SCRW"] > 10
