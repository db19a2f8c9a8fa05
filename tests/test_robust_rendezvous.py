"""Rendezvous (§6.5): both algorithms converge into X under disturbance and the
multiobjective PCBF (Algorithm 6.4) uses less fuel than the robust PCBF (Algorithm 5.2)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from balustrade.dsl.error_sets import is_rpi
from balustrade.reproduce.rendezvous import closed_loop, controllers, design


def test_rendezvous_short_horizon():
    d = design(N=20, T=40)
    system, s, error = d["system"], d["setup"], d["error"]
    assert is_rpi(error.E, system.A + system.B @ error.K, s.W, G=system.E, samples=300).ok
    ctls = controllers(d, (0.9,), record_h_r=True)
    res = {name: closed_loop(c, d, disturbed=True) for name, c in ctls.items()}
    for name, r in res.items():
        assert r["failures"] == 0, name
        assert r["final_in_X"] and r["stays_in_X_after_entry"], name
        assert r["final_h_r"] <= 1e-3, name
    h = res["robust"]["h_r"]
    assert np.all(np.diff(h) <= 1e-6 * np.maximum(1.0, h[:-1]) + 1e-5)   # Theorem 5.15
    ht = res["mo_rho0.9"]["h_tilde"]
    assert np.all(np.diff(ht) <= 1e-6 * np.maximum(1.0, ht[:-1]) + 1e-6)  # SPEC §4 item 7
    assert res["mo_rho0.9"]["fuel"] < res["robust"]["fuel"]


@pytest.mark.slow
def test_rendezvous_full_reproduction(tmp_path: Path):
    from balustrade.reproduce.rendezvous import run

    m = run(tmp_path, quick=False)
    for dist in ("disturbed", "nominal"):
        runs = m["runs"][dist]
        assert all(r["final_in_X"] for r in runs.values())
        assert runs["mo_rho0.9"]["fuel"] < runs["robust"]["fuel"]
    assert (tmp_path / "metrics.json").exists()
