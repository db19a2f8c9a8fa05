"""(4.5) in stage order (issue #15, step time): ``rapsf_problem(staged=True)`` makes
``(ẑ_{i+1}, α̂_{i+1})`` controls of stage ``i`` with the dynamics ``z_{i+1} = ẑ_{i+1}``,
``α_{i+1} = α̂_{i+1}``, so every tube row (4.5c) is a general constraint of one stage and the
stage-order pass (HPIPM inside ``sqpmethod``, target ``"structured-sqp"``) takes the problem
without running sums. The staged problem must have the optimum of the plain one."""

from __future__ import annotations

import numpy as np
import pytest

from balustrade.backends import compile
from balustrade.dsl.sets import Box
from balustrade.problems.rapsf import rapsf_problem, s_constants

N = 6


@pytest.fixture(scope="module")
def toy(rapsf_toy):
    return rapsf_toy                       # tests/conftest.py


def _problem(t, **kw):
    return rapsf_problem(t.sys, t.X0, t.F, t.G, t.W, t.K, N, **kw)


def _cases(t, count=8):
    """States inside X and boxes inside Θ₀ (vertex data as parameters)."""
    rng = np.random.default_rng(7)
    for _ in range(count):
        lo = rng.uniform(t.Theta0.lb, t.Theta0.ub)
        hi = rng.uniform(lo, t.Theta0.ub)
        V = Box(lo, hi).vertices()
        yield {"x0": rng.uniform(-0.8, 0.8, 2), "u_p": rng.uniform(-3, 3, 1),
               "theta": V.T, "s": s_constants(t.X0, t.sys, t.K, V)}


@pytest.mark.parametrize("factored", [False, True])
def test_staged_form_has_the_plain_optimum(toy, factored):
    plain = compile(_problem(toy, factored=factored), "fast-convex")
    staged = compile(_problem(toy, factored=factored, staged=True), "fast-convex")
    solved = 0
    for params in _cases(toy):
        a, b = plain.solve(params), staged.solve(params)
        assert a.status == b.status
        if a.status != "optimal":
            continue
        solved += 1
        # the cost pins v_0 only (the rest of the plan is not unique)
        np.testing.assert_allclose(b["v"][:, 0], a["v"][:, 0], rtol=0, atol=1e-7)
        assert abs(b.objective - a.objective) <= 1e-8 * (1 + abs(a.objective))
        z, zn = np.asarray(b["z"]), np.asarray(b["z_next"])
        np.testing.assert_allclose(zn, z[:, 1:], rtol=0, atol=1e-8)   # the stage copies
    assert solved >= 4


def test_staged_form_is_stage_local_for_hpipm(toy):
    """Through the stage-order pass every stage has the state ``(z_i, α_i)`` only (no
    running-sum states: no row couples two stages) and the controls ``(v_i, ẑ, α̂)``."""
    compiled = compile(_problem(toy, staged=True), "structured-sqp")
    qp = compiled.options["qpsol_options"]
    n, m = 2, 1
    assert qp["nx"] == [n + 1] * (N + 1)
    assert qp["nu"] == [m + n + 1] * N + [0]
    with pytest.raises(Exception, match="structure|stage|horizon"):  # the plain form is not
        compile(_problem(toy), "structured-sqp")


def test_staged_hpipm_solves_close_to_the_plain_optimum(toy):
    """HPIPM (``structured-sqp``) on the staged form: where it reports optimal, its input is
    the plain optimum's to HPIPM's accuracy (not the 1e-7 of the interior-point default;
    docs/adaptive.md)."""
    plain = compile(_problem(toy), "fast-convex")
    hp = compile(_problem(toy, staged=True), "structured-sqp")
    solved = 0
    for params in _cases(toy, 5):
        a, b = plain.solve(params), hp.solve(params)
        if a.status == "optimal" and b.status == "optimal":
            solved += 1
            np.testing.assert_allclose(b["v"][:, 0], a["v"][:, 0], rtol=0, atol=1e-4)
    assert solved >= 3
