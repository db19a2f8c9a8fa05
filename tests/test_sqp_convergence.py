"""The emittable SQP chain alone (sqpmethod + qrqp, no IPOPT retry) converges on the robust
slack problem (5.15) of the unstable 2-D example (Section 5.6, N = 10) — issue #14 §3.

Before the objective scaling of :func:`~balustrade.backends.casadi_backend.objective_scale`
and qrqp's ``min_lam`` it failed on about a third of random states
(``Search_Direction_Becomes_Too_Small``: qrqp cycled on rows with multipliers ~1e8)."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from test_emit_robust import EMITTABLE_TARGET, HIGH, LOW, N, _design

from balustrade.backends.casadi_backend import (
    OBJECTIVE_MAX_GRADIENT,
    CasadiCompiled,
    objective_scale,
    row_scale,
)
from balustrade.control.multiobjective import MultiobjectivePCBFController
from balustrade.models.unstable2d import unstable2d, unstable2d_setup


@pytest.fixture(scope="module")
def slack() -> CasadiCompiled:
    ctrl, _ = _design()
    return ctrl.slack.with_retries([])  # the emittable chain only: no retry at all


def test_emittable_chain_alone_solves_515(slack: CasadiCompiled) -> None:
    rng = np.random.default_rng(0)
    states = [rng.uniform(LOW, HIGH) for _ in range(50)]
    sols = [slack.solve({"x0": x}) for x in states]
    solved = sum(s.success for s in sols)
    assert solved >= 48, [s.message for s in sols if not s.success]  # >= 95 %
    assert all(s.solver == "sqpmethod" for s in sols)


def test_scaled_solution_reports_declared_cost_and_multipliers(slack: CasadiCompiled) -> None:
    """The scaling changes the solver's objective only: the reported objective is the
    declared cost (h_r ~ alpha_f · xi_N), the duals are those of the declared problem
    (stationarity in xi_N: alpha_f = multiplier of the terminal row + bound multiplier)."""
    assert 0.0 < slack.objective_scale < 1.0
    s = slack.solve({"x0": np.array([0.9, -11.9])})  # outside X: xi_N > 0, h_r ~ 1e9
    assert s.success, s.message
    xi_N = float(np.ravel(s.primal["xi_N"])[0])
    assert xi_N > 1.0
    assert s.objective == pytest.approx(1e6 * xi_N + float(np.sum(s.primal["xi"])), rel=1e-9)
    terminal = [k for k in s.dual if "terminal" in k]
    assert terminal, list(s.dual)
    lam = float(np.ravel(s.dual[terminal[0]])[-1])
    assert lam == pytest.approx(1e6, rel=1e-6)


def test_objective_scale_rule() -> None:
    x, p = ca.SX.sym("x", 2), ca.SX.sym("p")
    big = {"x": x, "p": p, "f": 1e6 * x[0] + x[1], "g": ca.SX(0, 1)}
    small = {"x": x, "p": p, "f": 0.5 * ca.sumsqr(x - p), "g": ca.SX(0, 1)}
    assert objective_scale(big, np.zeros(2), "sqpmethod") == OBJECTIVE_MAX_GRADIENT / 1e6
    assert objective_scale(big, np.zeros(2), "ipopt") == 1.0  # IPOPT scales by itself
    assert objective_scale(small, np.zeros(2), "sqpmethod") == 1.0
    nan = {"x": x, "p": p, "f": x[0] / p, "g": ca.SX(0, 1)}
    assert objective_scale(nan, np.zeros(2), "sqpmethod") == 1.0


def test_emittable_chain_alone_solves_615() -> None:
    """(6.15) of Algorithm 6.4 (its row (6.15g) carries ``α_f = 1e6``): row scaling takes
    the emittable chain alone from 0 to ~80 % of random states (measured 162 of 198)."""
    system, s = unstable2d(), unstable2d_setup(N)
    base, _ = _design()
    mo = MultiobjectivePCBFController.build(
        system, s.X, s.U, base.h_f, base.pi_f, N, s.deltas(), base.error, s.alpha_f,
        target=EMITTABLE_TARGET, slack_target=EMITTABLE_TARGET)
    mo.slack, mo.problem = mo.slack.with_retries([]), mo.problem.with_retries([])
    assert mo.problem.row_scale is not None
    rng = np.random.default_rng(0)
    ok = tried = 0
    for _ in range(50):
        x, u_p = rng.uniform(LOW, HIGH), rng.uniform(-4, 4, 1)
        mo.reset()
        _, info = mo.step(x, u_p)
        if "problem" in info.solutions:
            tried += 1
            ok += info.solutions["problem"].success
    assert tried >= 40 and ok >= 0.7 * tried, (ok, tried)


def test_row_scale_rule() -> None:
    x, p = ca.SX.sym("x", 2), ca.SX.sym("p")
    nlp = {"x": x, "p": p, "f": x[0], "g": ca.vertcat(1e6 * x[0] + x[1] - p, x[0] - x[1])}
    scale = row_scale(nlp, np.zeros(2), "sqpmethod")
    assert scale is not None and scale.tolist() == [OBJECTIVE_MAX_GRADIENT / 1e6, 1.0]
    assert row_scale(nlp, np.zeros(2), "ipopt") is None
    assert row_scale({**nlp, "g": x[0] - x[1]}, np.zeros(2), "sqpmethod") is None
