"""What the incremental RPI design's numbers prove (audit D, session 15): the LMIs of Claim 1
hold only to the SDP's tolerance, so ``info["proven_level"]`` records the level ``c`` at which
``{V <= c}`` is RPI by the LMIs as solved (``design.incremental_rpi.proven_level``)."""

from __future__ import annotations

import numpy as np
import pytest

from balustrade.design.incremental_rpi import proven_level
from balustrade.dsl.error_sets import bounded_vertices
from balustrade.dsl.sets import Box
from balustrade.problems.incremental_rpi import PolytopicLDI


def _scalar(a: float) -> PolytopicLDI:
    return PolytopicLDI(np.array([[a]]), (), np.zeros((0, 2)), np.array([[1.0]]),
                        Box([-1.0], [1.0]))


@pytest.mark.parametrize("a, lam, w", [(0.5, 0.5, 0.1), (0.9, 0.5, 0.0), (0.95, 0.3, 0.05)])
def test_scalar_cases_by_hand(a, lam, w):
    """``V = e²`` (P = 1), ``e⁺ = a e + w``: ``D = [[λ − a², −a w], [−a w, 1 − λ − w²]]``, whose
    smallest eigenvalue is worked out here in closed form; ``c = (1 − λ + η)/(1 − λ − η)``."""
    W = Box([-w], [w])
    eta, c = proven_level(_scalar(a), W, np.eye(1), np.eye(1), np.zeros((1, 1)), lam)
    p, q, r = lam - a * a, -a * w, 1 - lam - w * w
    lo = 0.5 * (p + r) - np.sqrt(0.25 * (p - r) ** 2 + q * q)
    want_eta = max(0.0, -lo)
    assert eta == pytest.approx(want_eta, abs=1e-14)
    want_c = (1 - lam + want_eta) / (1 - lam - want_eta) if lam + want_eta < 1 else np.inf
    assert c == pytest.approx(want_c, rel=1e-12)
    if want_eta == 0.0:
        assert c == 1.0                 # the LMIs hold exactly: E itself is proven


def test_marginal_system_is_not_proven():
    eta, c = proven_level(_scalar(1.0), Box([-0.1], [0.1]), np.eye(1), np.eye(1),
                          np.zeros((1, 1)), 0.9)
    assert eta > 0 and c == np.inf


def test_bicycle_design_records_its_proven_level():
    from balustrade.examples.bicycle import G_HEADING, bicycle_design

    d = bicycle_design(N=20, delta_step=1e-3)
    eta, c = d.error.info["lmi_residual"], d.error.info["proven_level"]
    assert 0.0 <= eta < 1e-3 and 1.0 <= c < 1.01
    # {V <= c} maps into itself at every Jacobian vertex and disturbance vertex (sampled)
    P, K = d.error.E.P, d.error.K
    rng = np.random.default_rng(0)
    s = rng.normal(size=(20000, 4))
    e = np.sqrt(c) * np.linalg.solve(np.linalg.cholesky(P).T,
                                     (s / np.linalg.norm(s, axis=1)[:, None]).T).T
    for A in d.ldi.vertices():
        for w in bounded_vertices(d.W) @ G_HEADING.T:
            en = e @ (A + d.ldi.B @ K).T + w
            assert np.einsum("ij,jk,ik->i", en, P, en).max() <= c
