"""Algorithms 5.2 and 6.4 emitted as C (:func:`balustrade.codegen.emit_robust`) decides exactly as
:class:`~balustrade.control.robust.RobustPCBFSafetyFilter`: same applied input, ``h_r``,
``h_cand``, fallback and status on random states, along a closed loop, on forced
failures of (5.15) (the candidate (5.17), then the projected proposal) and on NaN input;
:func:`balustrade.codegen.emit_multiobjective` as
:class:`~balustrade.control.multiobjective.MultiobjectivePCBFController` (Algorithm 6.4).

The system is the unstable 2-D system of Section 5.6 (reproduce/ch5_robust.py) with
N = 10, both problems on the emittable ``robust-sqp`` target; the Python side runs the
part of the retry chain the C has (:func:`~balustrade.codegen.mirror_c_retries`)."""

from __future__ import annotations

import dataclasses
import shutil
import warnings

import numpy as np
import pytest

from balustrade.codegen import (
    CMultiobjectivePCBFFilter,
    CRobustPCBFSafetyFilter,
    accelerate,
    build,
    emit_multiobjective,
    emit_problems,
    emit_robust,
)
from balustrade.codegen import cfiles as C
from balustrade.codegen.build import build_executable, run_under_valgrind
from balustrade.codegen.emit_robust import EMITTABLE_TARGET
from balustrade.codegen.runtime import mirror_c_retries
from balustrade.control.multiobjective import MultiobjectivePCBFController
from balustrade.control.robust import RobustPCBFSafetyFilter
from balustrade.design.rpi import ellipsoidal_rpi
from balustrade.design.terminal_cbf import synthesize_terminal_cbf
from balustrade.dsl.policies import AffinePolicy
from balustrade.errors import CodegenError, DegenerateResultWarning
from balustrade.models.unstable2d import W_BOUND, unstable2d, unstable2d_setup

N = 10
TOL = 1e-6
#: random states: a box around X = [-1, 1] x [-10, 10]
LOW, HIGH = np.array([-1.5, -12.0]), np.array([1.5, 12.0])


def _design(target: str = EMITTABLE_TARGET) -> tuple[RobustPCBFSafetyFilter, object]:
    system, s = unstable2d(), unstable2d_setup(N)
    error = ellipsoidal_rpi(system.A, system.B, s.W, s.X, s.U)
    X_E, U_E = error.tighten_state(s.X), error.tighten_input(s.U)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DegenerateResultWarning)
        cbf = synthesize_terminal_cbf(system.A, system.B, X_E, U_E, delta_N=s.deltas()[-1])
    # π_f as an explicit affine law: a numpy-only cbf.policy cannot be emitted (session 13)
    ctrl = RobustPCBFSafetyFilter.build(system, s.X, s.U, cbf, AffinePolicy(cbf.K), N,
                                        s.deltas(),
                                        error, s.alpha_f, slack_norm=1, target=target,
                                        slack_target=target)
    return ctrl, system


@pytest.fixture(scope="module")
def pair(tmp_path_factory: pytest.TempPathFactory) -> dict:
    py, system = _design()
    py.slack, py.filter = mirror_c_retries(py.slack), mirror_c_retries(py.filter)
    out = tmp_path_factory.mktemp("robust_c")
    emitted = emit_robust(py, "rob", out)
    lib = build(out, emitted.name, werror=True)
    return {"py": py, "c": CRobustPCBFSafetyFilter(lib), "system": system,
            "emitted": emitted}


def _kind(status: str) -> str:
    """The C cannot tell why a solve did not converge (``not_converged``); the backend can
    (``failed``, ``max_iterations``, ``feasible``: not a success for Algorithm 5.2)."""
    for why in ("max_iterations", "failed", "infeasible", "feasible"):
        status = status.replace(why, "not_converged")
    return status


def _same(py_out: tuple, c_out: tuple, where: str) -> None:
    (u1, i1), (u2, i2) = py_out, c_out
    assert np.max(np.abs(u1 - u2)) <= TOL, (where, u1, u2, i1.status, i2.status)
    assert i1.fallback == i2.fallback, (where, i1.fallback, i2.fallback)
    assert _kind(i1.status) == _kind(i2.status), (where, i1.status, i2.status)
    for key in ("h_r", "h_cand"):
        assert (key in i1.values) == (key in i2.values), (where, key, i1.values, i2.values)
        if key in i1.values:
            a, b = i1.values[key], i2.values[key]
            assert abs(a - b) <= TOL * max(1.0, abs(a)), (where, key, a, b)
    assert "candidate_exact" not in i2.values  # one input, quadratic h_f: always exact


def _random_states(pair: dict, n: int, seed: int) -> dict[str, int]:
    """C = Python on ``n`` random states (fresh controllers). A state where one solve
    converges in Python and not in C (or back) is counted, not compared: the C's BAL_OK
    tests the KKT residuals itself (bal/problem.c) and CasADi's sqpmethod its own, and on
    (5.15) with ``h_r ~ 1e9`` they disagree near ``tol_du`` (e.g. 1.013e-6 vs 1e-6 at the
    same point); at most 1% of the states may be such."""
    py, c = pair["py"], pair["c"]
    rng = np.random.default_rng(seed)
    seen: dict[str, int] = {"boundary": 0}
    for k in range(n):
        x, u_p = rng.uniform(LOW, HIGH), rng.uniform(-4, 4, 1)
        py.reset()
        c.reset()
        out_py, out_c = py.step(x, u_p), c.step(x, u_p)
        if _kind(out_py[1].status) != _kind(out_c[1].status):
            seen["boundary"] += 1
            continue
        _same(out_py, out_c, f"state {k}: {x}")
        seen[str(out_py[1].fallback)] = seen.get(str(out_py[1].fallback), 0) + 1
    assert seen["boundary"] <= max(1, n // 100), seen
    return seen


def test_c_equals_python_on_random_states(pair: dict) -> None:
    seen = _random_states(pair, 50, 0)
    assert seen.get("None", 0) >= 10, seen


@pytest.mark.slow
def test_c_equals_python_on_1000_random_states(pair: dict) -> None:
    seen = _random_states(pair, 1000, 1)
    assert seen.get("None", 0) >= 100, seen


def test_closed_loop_same_trace(pair: dict) -> None:
    """Warm starts and the candidate carried across steps: the same trajectory under the
    constant disturbance of Figure 5.2 (c_w = 1)."""
    py, c, system = pair["py"], pair["c"], pair["system"]
    py.reset()
    c.reset()
    x_py = x_c = unstable2d_setup(N).x0
    w = W_BOUND * np.ones(2)
    for k in range(25):
        out_py, out_c = py.step(x_py, np.array([2.5])), c.step(x_c, np.array([2.5]))
        _same(out_py, out_c, f"step {k}")
        x_py, x_c = system.step(x_py, out_py[0], w), system.step(x_c, out_c[0], w)
        assert np.max(np.abs(x_py - x_c)) <= 1e-5


def _failing_state(pair: dict) -> np.ndarray:
    """A state where (5.15) does not converge on this target, found among random states far
    outside X (|x| ~ 1e3; with the scaled SQP, states near X converge — 2 failures in 200 —
    while about 8 in 10 of these stop on a vanishing search direction)."""
    py = pair["py"]
    rng = np.random.default_rng(7)
    for _ in range(60):
        x = 1e3 * rng.uniform(LOW, HIGH)
        if not py.slack.solve({"x0": x}).success:
            return x
    raise AssertionError("no state found where (5.15) fails: the fallback test needs one")


def test_fallbacks_candidate_then_projected(pair: dict) -> None:
    """A failed (5.15) after a success applies the candidate (5.17) (and keeps shifting it);
    without a candidate, the projected proposal; a NaN state, the projected proposal with
    nothing solved; a NaN proposal, read as 0."""
    py, c = pair["py"], pair["c"]
    bad = _failing_state(pair)
    good = np.array([0.2, 0.5])
    for ctrl in (py, c):
        ctrl.reset()
    _same(py.step(good, [1.0]), c.step(good, [1.0]), "good")
    for k in range(3):
        out_py, out_c = py.step(bad, [1.0]), c.step(bad, [1.0])
        _same(out_py, out_c, f"failure {k}")
        assert out_c[1].fallback == "candidate"
        assert out_c[1].status.startswith("slack_")
    for ctrl in (py, c):
        ctrl.reset()
    out_py, out_c = py.step(bad, [9.0]), c.step(bad, [9.0])
    _same(out_py, out_c, "no candidate")
    assert out_c[1].fallback == "projected_proposal"
    assert out_c[0][0] == pytest.approx(2.5)  # 9 clipped to U = [-2.5, 2.5]
    out_py, out_c = py.step([np.nan, 0.0], [-7.0]), c.step([np.nan, 0.0], [-7.0])
    _same(out_py, out_c, "NaN state")
    assert out_c[1].status == "non_finite_state" and out_c[0][0] == -2.5
    py.reset()
    c.reset()
    out_py, out_c = py.step(good, [np.inf]), c.step(good, [np.inf])
    _same(out_py, out_c, "inf proposal")
    assert out_c[1].status.startswith("non_finite_proposal")


def test_non_emittable_target_names_the_one_to_use(tmp_path) -> None:
    ctrl, _ = _design("exact")  # IPOPT for both problems
    with pytest.raises(CodegenError, match=f"target='{EMITTABLE_TARGET}'.*slack_target"):
        emit_robust(ctrl, "rob", tmp_path)
    assert emit_problems  # the spec is still a ProblemsDeployment
    assert set(ctrl.deployment_spec().problems) == {"slack", "filter"}


VALGRIND_MAIN = r"""
#include <math.h>
#include <stdio.h>
#include "rob.h"
int main(void) {
  double x[2], u[1], h, up[1] = {2.5};
  int k, st, bad = 0;
  rob_work* wk = rob_alloc();
  if (!wk) return 2;
  for (k = 0; k < 12; ++k) {
    x[0] = -1.2 + 0.2 * k; x[1] = 11.0 - 2.0 * k;
    rob_step(x, up, u, &h, &st, wk);
    bad += !isfinite(u[0]);
  }
  x[0] = NAN;
  rob_step(x, up, u, &h, &st, wk);
  bad += st != BAL_ROBUST_BAD_INPUT;
  rob_free(wk);
  printf("%d\n", bad);
  return bad;
}
"""


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("valgrind") is None, reason="valgrind not installed")
def test_valgrind_clean(pair: dict) -> None:
    out = pair["emitted"].out_dir
    (out / "vg_main.c").write_text(VALGRIND_MAIN)
    exe = build_executable(out, "vg_main.c", extra_flags=["-g", "-O1"])
    run = run_under_valgrind(str(exe), timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]


# -- Algorithm 6.4 -------------------------------------------------------------------------
@pytest.fixture(scope="module")
def mo_pair(tmp_path_factory: pytest.TempPathFactory) -> dict:
    system, s = unstable2d(), unstable2d_setup(N)
    base, _ = _design()
    py = MultiobjectivePCBFController.build(
        system, s.X, s.U, base.h_f, base.pi_f, N, s.deltas(), base.error, s.alpha_f,
        target=EMITTABLE_TARGET, slack_target=EMITTABLE_TARGET)
    py.slack, py.problem = mirror_c_retries(py.slack), mirror_c_retries(py.problem)
    out = tmp_path_factory.mktemp("multiobj_c")
    emitted = emit_multiobjective(py, "mo", out)
    return {"py": py, "c": CMultiobjectivePCBFFilter(build(out, emitted.name, werror=True)),
            "system": system, "out": out}


def _same_mo(py_out: tuple, c_out: tuple, where: str) -> None:
    (u1, i1), (u2, i2) = py_out, c_out
    assert np.max(np.abs(u1 - u2)) <= TOL, (where, u1, u2, i1.status, i2.status)
    assert i1.fallback == i2.fallback, (where, i1.fallback, i2.fallback)
    assert _kind(i1.status) == _kind(i2.status), (where, i1.status, i2.status)
    assert set(i1.values) == set(i2.values), (where, i1.values, i2.values)
    for key, a in i1.values.items():
        assert abs(a - i2.values[key]) <= TOL * max(1.0, abs(a)), (where, key, a, i2.values)


def test_multiobjective_c_equals_python_along_closed_loops(mo_pair: dict) -> None:
    """Algorithm 6.4 from a few initial states, 6 steps each under the disturbance of
    Figure 5.2: the initialization by (5.15), (6.15) with the bound (6.15g), the candidate
    (6.14) as warm start and fallback, all as in Python (steps where one side's solve
    converges only at tol_du are skipped, as in :func:`_random_states`).

    With the sqpmethod scaling (casadi_backend.objective_scale/row_scale) (6.15) converges
    on most steps of the emittable chain; where it does not (Python's own chain ends with
    IPOPT, which has no C) the fallback "warm_start" (the candidate (6.14)) and its carried
    state are compared."""
    py, c, system = mo_pair["py"], mo_pair["c"], mo_pair["system"]
    rng = np.random.default_rng(3)
    starts = [unstable2d_setup(N).x0, *rng.uniform([-0.8, -5.0], [0.8, 5.0], (5, 2))]
    seen: dict[str, int] = {}
    w = W_BOUND * np.ones(2)
    for k, x in enumerate(starts):
        py.reset()
        c.reset()
        for j in range(6):
            out_py, out_c = py.step(x, [2.5]), c.step(x, [2.5])
            if _kind(out_py[1].status) != _kind(out_c[1].status):
                seen["boundary"] = seen.get("boundary", 0) + 1
                break
            _same_mo(out_py, out_c, f"start {k}, step {j}")
            seen[str(out_c[1].fallback)] = seen.get(str(out_c[1].fallback), 0) + 1
            x = system.step(x, out_py[0], w)
    compared = sum(v for k, v in seen.items() if k != "boundary")
    assert compared >= 20 and seen.get("None", 0) >= 10 and seen.get("warm_start", 0) >= 5, seen
    assert seen.get("boundary", 0) <= 1, seen


def _mo_random_states(mo_pair: dict, n: int, seed: int) -> dict[str, int]:
    """Algorithm 6.4, C = Python on ``n`` random states of the box of the closed-loop test,
    each from fresh controllers: the initialization by (5.15), then (6.15) from the
    candidate with the bound (6.15g); inputs, fallbacks, statuses and every recorded value
    within TOL. A state where one side's solve converges only at tol_du is counted, not
    compared (:func:`_random_states`); at most 1% may be such."""
    py, c = mo_pair["py"], mo_pair["c"]
    rng = np.random.default_rng(seed)
    seen: dict[str, int] = {"boundary": 0}
    for k in range(n):
        x, u_p = rng.uniform([-0.8, -5.0], [0.8, 5.0]), rng.uniform(-4, 4, 1)
        py.reset()
        c.reset()
        out_py, out_c = py.step(x, u_p), c.step(x, u_p)
        if _kind(out_py[1].status) != _kind(out_c[1].status):
            seen["boundary"] += 1
            continue
        _same_mo(out_py, out_c, f"state {k}: {x}")
        seen[str(out_py[1].fallback)] = seen.get(str(out_py[1].fallback), 0) + 1
    assert seen["boundary"] <= max(1, n // 100), seen
    return seen


@pytest.mark.slow
def test_multiobjective_c_equals_python_on_1000_random_states(mo_pair: dict) -> None:
    """The must-show of issue #14 for bal/multiobj.c: 1000 states (audit C, session 14)."""
    seen = _mo_random_states(mo_pair, 1000, 14)
    assert seen.get("None", 0) >= 100, seen


MO_VALGRIND_MAIN = r"""
#include <math.h>
#include <stdio.h>
#include "mo.h"
int main(void) {
  double x[2], u[1], up[1] = {2.5}, values[4];
  int k, st, bad = 0;
  mo_work* wk = mo_alloc();
  if (!wk) return 2;
  for (k = 0; k < 12; ++k) {
    x[0] = -0.8 + 0.15 * k; x[1] = 5.0 - 0.9 * k;
    mo_step(x, up, u, &st, wk);
    mo_values(wk, values);
    bad += !isfinite(u[0]);
    if (k == 5) mo_reset(wk);
  }
  x[0] = NAN;
  mo_step(x, up, u, &st, wk);
  bad += st != BAL_MULTIOBJ_BAD_INPUT;
  mo_free(wk);
  printf("%d\n", bad);
  return bad;
}
"""


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("valgrind") is None, reason="valgrind not installed")
def test_multiobjective_valgrind_clean(mo_pair: dict) -> None:
    """bal/multiobj.c under valgrind (audit C, session 14): initialization, (6.15) steps
    carrying the candidate, a reset, a NaN state; no memory error, no definite leak."""
    out = mo_pair["out"]
    (out / "vg_mo_main.c").write_text(MO_VALGRIND_MAIN)
    exe = build_executable(out, "vg_mo_main.c", extra_flags=["-g", "-O1"])
    run = run_under_valgrind(str(exe), timeout=600)
    assert run.returncode == 0, (run.stdout, run.stderr[-2000:])


def test_multiobjective_rejection_above_the_bound_c_equals_python(
        mo_pair: dict, tmp_path, monkeypatch) -> None:
    """A converged (6.15) rejected above the bound (``problem_above_bound``) is reported by
    the C as by Python, ``h_tilde_rejected`` included (``<name>_values`` out[3]). Forced by
    ``DECREASE_TOL = -1`` in Python and in the emitted ``mo_DECREASE_TOL``: every plan with
    ``h̃ > 0`` is rejected; inputs equal, statuses and all values equal."""
    import importlib

    emit_mod = importlib.import_module("balustrade.codegen.emit_robust")
    mo_mod = importlib.import_module("balustrade.control.multiobjective")

    py = mo_pair["py"]
    monkeypatch.setattr(mo_mod, "DECREASE_TOL", -1.0)
    monkeypatch.setattr(emit_mod, "DECREASE_TOL", -1.0)
    emitted = emit_multiobjective(py, "mo", tmp_path)
    c = CMultiobjectivePCBFFilter(build(tmp_path, emitted.name, werror=True))
    x = unstable2d_setup(N).x0
    py.reset()
    c.reset()
    rejected = 0
    for j in range(3):
        out_py, out_c = py.step(x, [2.5]), c.step(x, [2.5])
        _same_mo(out_py, out_c, f"step {j}")
        assert out_py[1].status == out_c[1].status, (out_py[1].status, out_c[1].status)
        rejected += out_c[1].status == "problem_above_bound"
        x = mo_pair["system"].step(x, out_py[0], W_BOUND * np.ones(2))
    assert rejected >= 2


def test_multiobjective_bad_input_and_refusals(mo_pair: dict, tmp_path) -> None:
    py, c = mo_pair["py"], mo_pair["c"]
    for ctrl in (py, c):
        ctrl.reset()
    out_py, out_c = py.step([np.inf, 0.0], [9.0]), c.step([np.inf, 0.0], [9.0])
    _same_mo(out_py, out_c, "inf state")
    assert out_c[1].status == "non_finite_state" and out_c[0][0] == 2.5
    spec = py.deployment_spec()
    with pytest.raises(CodegenError, match="record_h_r"):
        emit_multiobjective(dataclasses.replace(spec, record_h_r=True), "mo", tmp_path)
    with pytest.raises(CodegenError, match="expected a MultiobjectivePCBFController"):
        emit_multiobjective(object(), "mo", tmp_path)


def test_hand_built_spec_with_vector_h_f_is_refused(pair: dict, mo_pair: dict,
                                                    tmp_path) -> None:
    """A vector h_f would make <name>_post/<name>_cand write past the one double the C
    holds for xi_N, h_r, h~: refused before any C is written."""
    import casadi as ca

    for emit, spec in ((emit_robust, pair["py"].deployment_spec()),
                       (emit_multiobjective, mo_pair["py"].deployment_spec())):
        h_f = spec.h_f
        bad = dataclasses.replace(spec, h_f=lambda z, h_f=h_f: ca.vertcat(h_f(z), h_f(z)))
        with pytest.raises(CodegenError, match="h_f must be scalar"):
            emit(bad, "hb", tmp_path / emit.__name__)


def test_entry_points_listed_and_exported(pair: dict, mo_pair: dict) -> None:
    """Every entry point of bal/robust.h and bal/multiobj.h (``cfiles.ENTRY_POINTS``) is
    named in the generated header and exported by the built library."""
    for ctrl, kind, name in ((pair["c"], "robust", "rob"), (mo_pair["c"], "multiobj", "mo")):
        lib = ctrl._lib
        header = (lib.path.parent / f"{name}.h").read_text()
        for entry in C.ENTRY_POINTS[kind]:
            sym = f"{name}_{entry}"
            assert sym in header and hasattr(lib.lib, sym), sym


def test_accelerate_runs_the_robust_filter_on_its_c(pair: dict, tmp_path) -> None:
    """``accelerate`` knows Algorithm 5.2: the returned controller is the C filter and steps
    as the one emitted by hand."""
    acc = accelerate(pair["py"], build_dir=tmp_path)
    assert isinstance(acc, CRobustPCBFSafetyFilter)
    pair["c"].reset()
    for x in np.random.default_rng(3).uniform(LOW, HIGH, size=(5, 2)):
        _same(acc.step(x, np.array([0.5])), pair["c"].step(x, np.array([0.5])), f"x = {x}")


def test_the_c_above_candidate_code_reads_as_python_records_it():
    """``BAL_ROBUST_ABOVE_CANDIDATE`` (a converged (5.15) above the candidate's ``h̃``) is
    recorded as :class:`~balustrade.control.robust.RobustPCBFSafetyFilter` records it: status
    ``slack_above_candidate``, fallback ``candidate``, the value as ``h_r_local`` only."""
    from balustrade.codegen import status as S
    from balustrade.codegen.runtime_robust import robust_info

    code = S.code_of(S.ROBUST, "above_candidate")
    ok = S.code_of(S.SOLVE, "ok")
    info = robust_info(code, ok, S.code_of(S.SOLVE, "not_converged"), 102.6, 0.05)
    assert (info.status, info.fallback) == ("slack_above_candidate", "candidate")
    assert info.values == {"h_cand": 0.05, "h_r_local": 102.6}


@pytest.mark.slow
def test_lane_change_seed_26_c_never_takes_a_slack_solve_above_the_candidate():
    """Seed 26 of the lane change (configuration ``converging``): the emitted (5.15) converged
    at step 8 to a local solution with ``h_r`` 102.6 while the candidate had ``h̃`` 0.050; the
    C now applies the candidate there, as Python does for such a solve, and ``h_r`` is
    non-increasing (issue #16)."""
    from balustrade.codegen import accelerate
    from balustrade.reproduce import lane_change as L

    cfg = L.config("converging")
    d = L.design(cfg)
    c = accelerate(L.controllers(d, rho=cfg.rho)["robust"])
    x, last = L.X0.copy(), np.inf
    for w in L.disturbances(d, 26, 12):
        u, info = c.step(x, L.human(x))
        h = info.values.get("h_r", info.values.get("h_cand", np.nan))
        if "h_r" in info.values and "h_cand" in info.values:
            assert info.values["h_r"] <= info.values["h_cand"] + 1e-5
        if np.isfinite(h):
            assert h <= last + 1e-5
            last = h
        x = d.system.step(x, u, w)
