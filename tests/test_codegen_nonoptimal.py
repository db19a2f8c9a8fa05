"""A (2.24) solve that ends merely ``feasible`` (not converged) is handled by the emitted C
step exactly as by :class:`~balustrade.control.pcbf.PCBFSafetyFilter` (issue #12): its cost
is an upper bound on ``h_PB`` (``h_PB`` NaN, ``h_PB_upper`` recorded), the step is a failed
(2.24) (the shifted plan), and only without a plan are its slacks used in (2.23)
(``"feasible_slack"``); a feasible point of cost 0 is optimal (``h_PB >= 0``).

Non-convergence is forced in both by the same options: ``sqpmethod`` with an unreachable
dual tolerance and 3 iterations, so every (2.24) solve stops primal feasible at
``max_iter`` (the C's BAL_OK uses the same ``tol_du``)."""

from __future__ import annotations

import numpy as np
import pytest

from balustrade.backends import compile, resolve_target
from balustrade.codegen import CPCBFSafetyFilter, build, emit_pcbf
from balustrade.codegen.runtime import mirror_c_retries
from balustrade.examples.codegen import pendulum_pcbf_filter
from balustrade.models.pendulum import pendulum

#: (2.24) never converges: its dual residual cannot get below 1e-30
TRUNCATED = {"max_iter": 3, "tol_du": 1e-30}


@pytest.fixture(scope="module")
def truncated(tmp_path_factory: pytest.TempPathFactory) -> dict:
    py = pendulum_pcbf_filter()
    py.slack = mirror_c_retries(compile(py.slack.ocp, "casadi", "sqpmethod", TRUNCATED))
    py.filter = mirror_c_retries(py.filter)
    out = tmp_path_factory.mktemp("pcbf_truncated")
    emitted = emit_pcbf(py, "trunc", out)
    return {"py": py, "c": CPCBFSafetyFilter(build(out, emitted.name, werror=True))}


def _status(status: str) -> str:
    """The C cannot tell why a solve did not converge (BAL_NOT_CONVERGED); the backend
    can (``max_iterations``, ``failed``, ``infeasible``)."""
    for why in ("max_iterations", "failed", "infeasible"):
        status = status.replace(why, "not_converged")
    return status


def _same(i1, i2, u1, u2, where) -> None:
    assert (_status(i1.status), i1.fallback) == (i2.status, i2.fallback), where
    assert i1.uncertified == i2.uncertified, where
    assert np.abs(u1 - u2).max() <= 1e-6, (where, u1, u2)
    for key in ("h_PB", "h_PB_upper"):
        a, b = i1.values.get(key), i2.values.get(key)
        assert (a is None) == (b is None), (where, key)
        if a is not None:
            assert np.isnan(a) == np.isnan(b) and (np.isnan(a) or abs(a - b) <= 1e-6), where


def test_feasible_slack_decisions_equal_python(truncated: dict) -> None:
    py, c = truncated["py"], truncated["c"]
    system = pendulum()
    seen = set()
    for x0, proposal in (([0.49, 0.5], 2.0), ([0.45, -1.2], -3.0), ([0.0, 0.0], 2.0),
                         ([0.6, 1.2], 3.0)):
        py.reset()
        c.reset()
        x1 = x2 = np.array(x0)
        for k in range(14):
            u1, i1 = py.step(x1, np.array([proposal]))
            u2, i2 = c.step(x2, np.array([proposal]))
            _same(i1, i2, u1, u2, (x0, k))
            seen.add((i1.fallback, i1.status.split("_filter")[0]))
            x1, x2 = system.step(x1, u1), system.step(x2, u2)
    # every branch was taken: certified (cost 0), failed (2.24) with a plan, without one
    assert (None, "ok") in seen
    assert ("shifted_plan", "slack_feasible") in seen
    assert ("feasible_slack", "slack_feasible") in seen


@pytest.fixture(scope="module")
def truncated_approx(tmp_path_factory: pytest.TempPathFactory) -> dict:
    from balustrade.codegen import CApproximatePCBFFilter, emit_approximate
    from balustrade.control.approximate import ApproximatePCBFFilter
    from balustrade.design.terminal_cbf import synthesize_terminal_cbf
    from balustrade.models.pendulum import pendulum_setup

    system, s = pendulum(), pendulum_setup()
    h = synthesize_terminal_cbf(system.A, system.B, s.X, s.U, delta_N=s.deltas[-1])
    # one SQP iteration: (7.6) (bounds only) ends feasible, (7.5) feasible or not
    py = ApproximatePCBFFilter(system, s.U, h,
                               target=resolve_target("fast-sqp", options={"max_iter": 1}))
    py.decrease.compiled = mirror_c_retries(py.decrease.compiled)
    py.filter = mirror_c_retries(py.filter)
    out = tmp_path_factory.mktemp("approx_truncated")
    emitted = emit_approximate(py, "atrunc", out)
    return {"py": py, "c": CApproximatePCBFFilter(build(out, emitted.name, werror=True))}


def test_approximate_feasible_solves_equal_python(truncated_approx: dict) -> None:
    """Algorithm 7.5 with (7.6) and (7.5) that never converge: a feasible (7.6) point is a
    candidate and a feasible (7.5) point is applied (``"filter_feasible"``, flagged), in
    Python as in C (the C used to apply it as ``"ok"``, Python to discard it)."""
    py, c = truncated_approx["py"], truncated_approx["c"]
    rng = np.random.default_rng(5)
    statuses = []
    for x, u_p in zip(rng.uniform([-0.7, -2.0], [0.7, 2.0], size=(150, 2)),
                      rng.uniform(-4, 4, size=(150, 1))):
        u1, i1 = py.step(x, u_p)
        u2, i2 = c.step(x, u_p)
        # the C names every failed (7.5) "filter_failed" (BAL_APPROX_MAX_DECREASE)
        status = "filter_failed" if i1.fallback == "max_decrease_solution" else i1.status
        assert (status, i1.fallback, i1.uncertified) == \
            (i2.status, i2.fallback, i2.uncertified), (x, u_p)
        assert np.abs(u1 - u2).max() <= 1e-6, (x, u_p, u1, u2)
        statuses.append(status)
    assert {"filter_feasible", "certified", "ok", "filter_failed"} <= set(statuses)
