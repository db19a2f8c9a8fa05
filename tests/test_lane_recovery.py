"""Recovery steps run the interior-point attempt of the retry chain first (issue #14, the
lane change's worst steps: the SQP attempts fail on the LP-like slack problems while
``h_r > 0`` and cost 150–240 ms each, the interior-point solver alone 21–50 ms).

On the unstable 2-D example of Section 5.6 with ``robust-sqp`` (the lane change's target):
Algorithm 5.2 leads (5.15) with the chain's interior-point retry at the first step (no
candidate; since session 13, when the C tells the interior-point solver's acceptable stop
as Python does) and where its candidate does not certify ``h_r = 0``, not where it does;
Algorithm 6.4 leads its first (5.15) and (6.15) and not the next (6.15). The
emitted C runs the same attempts: its attempt counters ``<P>_attempts`` equal Python's runs,
and the C decides as Python.
"""

from __future__ import annotations

import ctypes

import numpy as np
import pytest
from test_emit_robust import _design, _kind
from test_retry_dedup import _counted

from balustrade.backends import PRESETS, recovery_lead
from balustrade.backends.targets import target
from balustrade.codegen import accelerate
from balustrade.control.multiobjective import MultiobjectivePCBFController
from balustrade.models.unstable2d import unstable2d, unstable2d_setup

#: states outside S_r (h_r > 0) of the 2-D example, and the origin (inside)
OUTSIDE = [np.array([0.9, 8.0]), np.array([-0.95, -9.0]), np.array([0.8, 9.5])]
ORIGIN = np.zeros(2)


def _lead_solver(compiled):
    lead = recovery_lead(compiled, "recovery")
    assert lead is not None  # robust-sqp's chain ends with the interior-point retry
    return compiled._retry_solvers()[lead], compiled.retries[lead][0]


def test_recovery_lead_is_the_chains_interior_point_retry() -> None:
    ctrl, _ = _design()
    assert ctrl.recovery_target == "recovery" and PRESETS["recovery"].backend == "casadi"
    k = recovery_lead(ctrl.slack, "recovery")
    assert ctrl.slack.retries[k][0] == PRESETS["recovery"].nlp_solver
    assert recovery_lead(ctrl.slack, None) is None
    # a chain without retries has nothing to reorder
    assert recovery_lead(ctrl.slack.with_retries([]), "recovery") is None


def test_chain_that_starts_with_the_recovery_solver_is_not_reordered() -> None:
    """``exact`` runs IPOPT first and has IPOPT again as its cold retry, the very attempt
    ``"recovery"`` names: its first attempt already is the lead, so nothing is reordered
    (a recovery step would otherwise run the cold retry before the warm first attempt)."""
    ctrl, _ = _design("exact")
    rec = PRESETS["recovery"]
    assert ctrl.slack.solver_name == rec.nlp_solver
    assert (rec.nlp_solver, {}) in [(n, dict(o)) for n, o in ctrl.slack.retries]
    assert recovery_lead(ctrl.slack, "recovery") is None
    assert recovery_lead(ctrl.filter, "recovery") is None


def test_robust_recovery_step_runs_the_interior_point_attempt_first() -> None:
    ctrl, _ = _design()
    runs = _counted(ctrl.slack)
    led, name = _lead_solver(ctrl.slack)
    for x in OUTSIDE:
        ctrl.reset()
        assert ctrl.recovering()  # the first step: no candidate certifies anything
        runs.clear()
        ctrl.step(x, np.array([1.0]))
        assert runs[0] is led, (x, runs)
        assert ctrl.recovering()  # outside S_r: the candidate's h~ is positive
        runs.clear()
        u, info = ctrl.step(x, np.array([1.0]))
        assert runs[0] is led, (x, runs)
        assert runs.count(led) == 1  # not run again as the last resort
        s = info.solutions["slack"]
        assert s.solver == name and len(runs) == 1, (x, s.solver, s.message)
        assert info.values["h_r"] > 0
    # from the origin the candidate certifies h_r = 0 at the next step: the SQP leads
    ctrl.reset()
    runs.clear()
    ctrl.step(ORIGIN, np.array([0.0]))
    assert runs[0] is led  # the first step leads, wherever it starts
    assert not ctrl.recovering()
    runs.clear()
    ctrl.step(ORIGIN, np.array([0.0]))
    assert runs[0] is ctrl.slack.solver


def test_robust_first_step_leads_the_filter_problem_too() -> None:
    """Without a candidate (the first step, and after a reset) (5.16) runs the chain's
    interior-point retry first (``filter_lead``, session 15); with a candidate its SQP leads,
    recovery step or not."""
    ctrl, _ = _design()
    runs = _counted(ctrl.filter)
    led, _ = _lead_solver(ctrl.filter)
    assert ctrl.filter_lead == recovery_lead(ctrl.filter, "recovery")
    for x in [*OUTSIDE, ORIGIN]:
        ctrl.reset()
        runs.clear()
        ctrl.step(x, np.array([1.0]))
        assert runs[0] is led and runs.count(led) == 1, (x, runs)
        runs.clear()
        ctrl.step(x, np.array([1.0]))
        assert runs[0] is ctrl.filter.solver, (x, runs)


def test_robust_without_recovery_target_keeps_the_chain_order() -> None:
    ctrl, _ = _design()
    ctrl.recovery_target = None
    runs = _counted(ctrl.slack)
    for _ in range(2):
        runs.clear()
        ctrl.step(OUTSIDE[0], np.array([1.0]))
        assert runs[0] is ctrl.slack.solver


def _mo() -> MultiobjectivePCBFController:
    base, _ = _design()
    s = unstable2d_setup(10)
    return MultiobjectivePCBFController.build(
        unstable2d(), s.X, s.U, base.h_f, base.pi_f, 10, s.deltas(), base.error, s.alpha_f,
        target="robust-sqp", slack_target="robust-sqp")


def test_multiobjective_leads_its_first_solves_only() -> None:
    ctrl = _mo()
    slack_runs, runs = _counted(ctrl.slack), _counted(ctrl.problem)
    led_s, _ = _lead_solver(ctrl.slack)
    led_p, name = _lead_solver(ctrl.problem)
    x = OUTSIDE[0]
    u, info = ctrl.step(x, np.array([1.0]))
    assert slack_runs[0] is led_s and runs[0] is led_p
    assert info.solutions["problem"].solver == name and info.status == "ok"
    assert not ctrl.recovering()
    runs.clear()
    x = ctrl.system.step(x, u, np.zeros(ctrl.system.nw) if ctrl.system.nw else None)
    ctrl.step(np.asarray(x, dtype=float).reshape(-1), np.array([1.0]))
    assert runs[0] is ctrl.problem.solver  # the next (6.15): the SQP leads again


@pytest.fixture(scope="module")
def robust_c(tmp_path_factory: pytest.TempPathFactory) -> tuple:
    # SQP attempts capped at a few iterations (as tests/test_lane_c_chain.py): they fail
    # where the lane's do, so the attempt counts tell a led solve from the usual order
    py, _ = _design(target("robust-sqp", options={"max_iter": 3}))
    return py, accelerate(py, build_dir=tmp_path_factory.mktemp("recovery"), name="rec")


def test_c_runs_the_same_attempts_as_python(robust_c: tuple) -> None:
    """The C's ``<P>_attempts`` of (5.15) equal Python's runs along a loop over states
    outside ``S_r`` (recovery steps, led by the interior-point attempt: one run; the first
    step too) and at the origin (the SQP first), with the same statuses and inputs. Fails on
    a C that does not lead: its SQP attempts, warm-started from the previous state, fail
    first (three runs)."""
    py, c = robust_c
    attempts = c._lib.fn(f"{c.slack.info['prefix']}_attempts", ctypes.c_int,
                         [ctypes.c_void_p])
    fattempts = c._lib.fn(f"{c.filter.info['prefix']}_attempts", ctypes.c_int,
                          [ctypes.c_void_p])
    runs, filter_runs = _counted(py.slack), _counted(py.filter)
    led, _ = _lead_solver(py.slack)
    filter_led, _ = _lead_solver(py.filter)
    seen_led = seen_sqp = seen_filter = 0
    py.reset()
    c.reset()
    for k, x in enumerate([*OUTSIDE, *OUTSIDE[::-1], ORIGIN, ORIGIN]):
        runs.clear()
        filter_runs.clear()
        (u1, i1), (u2, i2) = py.step(x, np.array([1.0])), c.step(x, np.array([1.0]))
        assert (i1.status, i1.fallback) == (i2.status, i2.fallback), (x, i1.status)
        assert np.max(np.abs(u1 - u2)) <= 1e-6, (x, u1, u2)
        assert attempts(c.slack.work) == len(runs), (x, attempts(c.slack.work), len(runs))
        # (5.16), where it ran (not after a failed (5.15)): led by the interior-point
        # attempt at the first step only (no candidate)
        assert filter_runs or k > 0
        if filter_runs:
            assert fattempts(c.filter.work) == len(filter_runs), (
                k, fattempts(c.filter.work), len(filter_runs))
            assert (filter_runs[0] is filter_led) == (k == 0), (k, filter_runs)
            # the same attempt answered: the same point to the last bit (tests/
            # test_lane_sync.py; an SQP answer differs from the interior-point one there)
            assert np.array_equal(u1, u2), (k, u1 - u2)
            seen_filter += 1
        seen_led += runs[0] is led
        seen_sqp += runs[0] is py.slack.solver
    # led: the first step (no candidate) and the steps after an outside state; the SQP
    # first: the second step at the origin
    assert seen_led >= 6 and seen_sqp >= 1 and seen_filter >= 4, (seen_led, seen_sqp,
                                                                    seen_filter)


@pytest.fixture(scope="module")
def mo_c(tmp_path_factory: pytest.TempPathFactory) -> tuple:
    base, _ = _design()
    s = unstable2d_setup(10)
    capped = target("robust-sqp", options={"max_iter": 3})
    py = MultiobjectivePCBFController.build(
        unstable2d(), s.X, s.U, base.h_f, base.pi_f, 10, s.deltas(), base.error, s.alpha_f,
        target=capped, slack_target=capped)
    return py, accelerate(py, build_dir=tmp_path_factory.mktemp("mo_recovery"), name="morec")


def test_multiobjective_c_runs_the_same_attempts_as_python(mo_c: tuple) -> None:
    """Algorithm 6.4 in C: the attempts of (5.15) at the first step and of each (6.15) equal
    Python's runs (the first (6.15) led by the interior-point attempt, the next ones by the
    SQP from the candidate), with the same statuses and inputs."""
    py, c = mo_c
    fn = {k: c._lib.fn(f"{v.info['prefix']}_attempts", ctypes.c_int, [ctypes.c_void_p])
          for k, v in (("slack", c.slack), ("problem", c.problem))}
    runs = {"slack": _counted(py.slack), "problem": _counted(py.problem)}
    led, _ = _lead_solver(py.problem)
    py.reset()
    c.reset()
    x, firsts = OUTSIDE[0], []
    for k in range(5):
        for r in runs.values():
            r.clear()
        (u1, i1), (u2, i2) = py.step(x, np.array([1.0])), c.step(x, np.array([1.0]))
        assert (_kind(i1.status), i1.fallback) == (_kind(i2.status), i2.fallback), k
        assert np.max(np.abs(u1 - u2)) <= 1e-6, (k, u1, u2)
        assert fn["problem"](c.problem.work) == len(runs["problem"]), k
        if k == 0:
            assert fn["slack"](c.slack.work) == len(runs["slack"])
        firsts.append(runs["problem"][0] is led)
        x = np.asarray(py.system.step(x, u1, np.zeros(py.system.nw) if py.system.nw else None),
                       dtype=float).reshape(-1)
    assert firsts == [True, False, False, False, False], firsts


def test_c_lead_is_the_c_attempt_running_the_lead() -> None:
    """The emitted ``<name>_SLACK_LEAD`` is the C attempt that runs the chain's lead
    (``_Problem.c_attempt``, the mapping ``second_solver`` uses too): the interior-point
    retry with the whole chain emitted, none when ``full_chain=False`` leaves it out."""
    from balustrade.codegen.emit import _Problem
    from balustrade.codegen.emit_robust import _c_lead

    ctrl, _ = _design()
    k = recovery_lead(ctrl.slack, "recovery")
    full = _Problem(ctrl.slack, "q_slack", "(5.15)", "q", None, True)
    part = _Problem(ctrl.slack, "q_slack", "(5.15)", "q", None, False)
    j = _c_lead(full, "recovery")
    assert j == full.c_attempt[k + 1] and j > 0
    assert full.solvers[j][1] == ctrl.slack.retries[k][0] == "ipopt"
    assert _c_lead(part, "recovery") == 0 and part.c_attempt[k + 1] is None
    assert _c_lead(full, None) == 0
