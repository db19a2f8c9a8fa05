"""Section 7.5 reproduction (SPEC §3.5): Table 7.1 in direction and the closed loop of
Figure 7.1, on the quick configuration (coarse grid, 600 evaluation states)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from balustrade.reproduce import pendulum_approx


@pytest.fixture(scope="module")
def quick(tmp_path_factory) -> dict:
    out = tmp_path_factory.mktemp("pendulum_approx")
    metrics = pendulum_approx.run(out, quick=True)
    assert (out / "metrics.json").exists() and (out / "figure7_1.png").stat().st_size > 10_000
    assert json.loads((out / "metrics.json").read_text())["quick"] is True
    return metrics


def test_table_7_1_direction(quick):
    t = quick["table7_1"]["table"]
    d, s = t["D_PB \\ S_PB"], t["S_PB"]
    assert quick["table7_1"]["fallbacks"] == 0            # (7.5) feasible everywhere (Prop. 7.3)
    assert quick["table7_1"]["n_S_PB"] > 0 and quick["table7_1"]["n_D_PB_minus_S_PB"] > 0
    # the extended h intervenes markedly less than h_PB inside S_PB (thesis 3.50 vs 9.33)
    assert s["h rho=1"] < 0.95 * s["h_PB rho=1"]
    assert s["h rho=0.2"] < s["h_PB rho=0.2"]
    # both approximations intervene more than the PCBF inside S_PB (learning errors)
    assert s["h_PB rho=1"] > 1.5 and s["h rho=1"] > 1.5
    # rho = 0.2 roughly halves interventions in D_PB \ S_PB (thesis 0.41/0.48 vs 1.05/1.10)
    for name in ("h_PB", "h"):
        assert d[f"{name} rho=0.2"] < 0.65 * d[f"{name} rho=1"]
    # at rho = 1, within ±20 % of the PCBF in D_PB \ S_PB (SPEC §3.5 SOFT)
    assert 0.8 <= d["h_PB rho=1"] <= 1.2 and 0.8 <= d["h rho=1"] <= 1.2
    assert "Table 7.1" in quick["summary_table"] and "9.33" in quick["summary_table"]


def test_figure_7_1_closed_loop(quick):
    loop = quick["closed_loop"]
    pcbf = [loop[f"PCBF w0={w:g}"] for w in pendulum_approx.OMEGA0]
    approx = [loop[f"approx w0={w:g}"] for w in pendulum_approx.OMEGA0]
    # both converge to the constraint psi = 0.5, the approximate filter more slowly
    assert all(r["steps_to_psi_0.5"] is not None for r in pcbf + approx)
    assert np.mean([r["steps_to_psi_0.5"] for r in approx]) > \
        1.5 * np.mean([r["steps_to_psi_0.5"] for r in pcbf])
    # once inside S_PB, the state stays in X
    for r in pcbf + approx:
        assert r["first_step_in_S_PB"] is not None
        assert r["max_violation_after_entering_S_PB"] <= 1e-6
        assert r["fallbacks"] == 0
    assert sum(r["certified_steps"] for r in approx) > 0


@pytest.mark.slow
def test_full_reproduction(tmp_path):
    m = pendulum_approx.run(tmp_path, quick=False)
    t = m["table7_1"]["table"]
    assert m["table7_1"]["n_states"] == 10_000 and m["table7_1"]["fallbacks"] == 0
    assert t["S_PB"]["h rho=1"] < t["S_PB"]["h_PB rho=1"]
    assert t["D_PB \\ S_PB"]["h rho=0.2"] < 0.65 * t["D_PB \\ S_PB"]["h rho=1"]
