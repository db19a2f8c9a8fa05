"""Rendezvous (§6.5): both algorithms converge into X under disturbance and the
multiobjective PCBF (Algorithm 6.4) uses less fuel than the robust PCBF (Algorithm 5.2)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from balustrade.dsl.error_sets import is_rpi
from balustrade.errors import BalustradeError, NonFiniteError
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


def test_candidate_and_membership_shortcuts_match_their_definitions():
    """The vectorized slack shift of the candidate (5.17) equals the entrywise formula
    ``ξ̃_i = max(0, ξ_{i+1} + Δ_i − Δ_{i+1})`` exactly, and the NumPy ``Polytope.contains`` /
    ``n_rows`` agree with the set's CasADi definition (``c(x) <= tol``, the rows of ``c``),
    also at points on the boundary and outside; a non-finite point is refused."""
    import casadi as ca

    from balustrade.control.robust_steps import robust_candidate
    from balustrade.dsl.sets_base import Set

    d = design(N=8, T=10)
    system, s, error, cbf = d["system"], d["setup"], d["error"], d["cbf"]
    X_E, U_E = error.tighten_state(s.X), error.tighten_input(s.U)
    rng = np.random.default_rng(3)
    N, r = s.N, X_E.H.shape[0]
    assert X_E.n_rows == Set.n_rows.fget(X_E) == r
    deltas = np.sort(rng.uniform(0.0, 0.5, N))
    z, v = rng.normal(size=(6, N + 1)), rng.normal(size=(3, N))
    xi = np.maximum(rng.normal(size=(r, N)), 0.0)
    cand = robust_candidate(system, X_E, cbf, cbf.policy, deltas, z, v, xi, U_E)
    for i in range(N - 1):
        assert np.array_equal(cand.xi[:, i],
                              np.maximum(0.0, xi[:, i + 1] + (deltas[i] - deltas[i + 1])))
    assert np.array_equal(cand.xi[:, N - 1], np.maximum(0.0, X_E.H @ z[:, N] - X_E.h
                                                        + deltas[N - 1]))
    with pytest.raises(BalustradeError, match="xi of shape"):
        robust_candidate(system, X_E, cbf, cbf.policy, deltas, z, v, xi[:, :-1], U_E)
    a = U_E.H[0]
    corner = U_E.h[0] * a / (a @ a)                       # on the first row's hyperplane
    for u in [np.zeros(3), 1e3 * np.ones(3), corner, *rng.normal(scale=20.0, size=(50, 3))]:
        by_c = bool(np.all(np.asarray(ca.evalf(U_E.c(ca.DM(u)))).ravel() <= 1e-12))
        assert U_E.contains(u, tol=1e-12) == by_c
    with pytest.raises(NonFiniteError):
        U_E.contains(np.array([np.nan, 0.0, 0.0]), tol=1e-12)
