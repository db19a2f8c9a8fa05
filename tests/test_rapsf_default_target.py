"""RAPSF's default target is ``fast-convex-sized`` (the direct QP backend: DAQP on small (4.5),
PIQP on large, row generation on large problems; session 14, before it ``fast-convex``), the one
docs/adaptive.md calls the Python default, and it gives the inputs
``exact`` (IPOPT) gives (audit session 13, finding 7; measured on 3 and 8 masses by
``benchmarks/rapsf_default_target.py``)."""

from __future__ import annotations

import numpy as np

from balustrade.control.rapsf import RAPSF
from balustrade.estimate import BoxUpdate

N = 5


def test_default_is_fast_convex_with_the_inputs_of_exact(rapsf_toy) -> None:
    t = rapsf_toy

    def make(**kw: object) -> RAPSF:
        return RAPSF(t.sys, t.X0, t.F, t.G, t.W, t.K, N, t.Theta0,
                     estimator=BoxUpdate(t.sys, t.W, t.Theta0), **kw)

    default, exact = make(), make(target="exact")
    assert default.target.name == "fast-convex-sized" and default.target.is_preset()
    rng = np.random.default_rng(5)
    x, theta = np.array([0.9, 0.2]), np.array([1.2, 0.3])
    for k in range(8):
        u_p = np.array([3.0 * np.sin(0.4 * k) + 1.5])      # aggressive: the filter acts
        (u_d, i_d), (u_e, i_e) = default.step(x, u_p), exact.step(x, u_p)
        assert i_d.fallback == i_e.fallback and i_d.status == i_e.status, (k, i_d, i_e)
        assert np.max(np.abs(u_d - u_e)) <= 1e-6, (k, u_d, u_e)
        x = t.sys.step(x, u_d, theta, rng.uniform(-0.004, 0.004, 2))


def test_warm_start_on_the_default_target_warns(rapsf_toy) -> None:
    """``warm_start=True`` does nothing on the direct backend (no starting point): the user
    is told at construction instead of losing warm starts silently (review, session 13)."""
    import pytest

    t = rapsf_toy
    args = (t.sys, t.X0, t.F, t.G, t.W, t.K, N, t.Theta0)
    with pytest.warns(UserWarning, match="warm_start=True has no effect"):
        RAPSF(*args, warm_start=True)
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        RAPSF(*args, warm_start=True, target="convex-qp")
        RAPSF(*args)
