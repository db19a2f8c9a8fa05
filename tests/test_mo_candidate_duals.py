"""Algorithm 6.4's ``candidate_duals`` (issue #14, lane change, session 14): ordinary (6.15)
solves start from the candidate (6.14) with the multipliers of the previous converged
(6.15), in Python (``CasadiCompiled.solve``'s ``duals_from``) and in the emitted C
(``<name>_CANDIDATE_DUALS``, ``bal/multiobj.c``). Measured on the lane change in
docs/vehicles.md, "Session 14"; opt-in (default ``False``).

On the unstable 2-D example of Section 5.6 (N = 10), as tests/test_lane_sync.py.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_emit_robust import _design, _kind

from balustrade.backends import Solution
from balustrade.backends.casadi_backend import CasadiCompiled
from balustrade.backends.targets import target
from balustrade.codegen import accelerate
from balustrade.codegen.emit_robust import EMITTABLE_TARGET
from balustrade.control.multiobjective import MultiobjectivePCBFController
from balustrade.errors import BalustradeError
from balustrade.models.unstable2d import W_BOUND, unstable2d_setup

N = 10
STEPS = 20


def _controller(candidate_duals: bool = True, candidate_second: bool = False,
                capped: bool | None = None) -> MultiobjectivePCBFController:
    """Algorithm 6.4 on the emittable target; with ``candidate_second`` its SQP capped at 10
    iterations, so that first attempts of ordinary steps fail (18 of the loops below) and
    the second start runs."""
    robust, system = _design()
    s = unstable2d_setup(N)
    capped = candidate_second if capped is None else capped
    tgt = target(EMITTABLE_TARGET, options={"max_iter": 10}) if capped else EMITTABLE_TARGET
    return MultiobjectivePCBFController.build(
        system, s.X, s.U, robust.h_f, robust.pi_f, N, s.deltas(), robust.error, s.alpha_f,
        rho=0.5, target=tgt, slack_target=tgt,
        candidate_duals=candidate_duals, candidate_second=candidate_second)


def _loop(ctrl: object, x0: np.ndarray, rng_seed: int, system: object = None
          ) -> tuple[np.ndarray, list]:
    system = ctrl.system if system is None else system
    rng = np.random.default_rng(rng_seed)
    ctrl.reset()
    x, us, infos = np.asarray(x0, dtype=float), [], []
    for _ in range(STEPS):
        u, info = ctrl.step(x, np.array([2.5]))
        us.append(np.array(u))
        infos.append(info)
        x = system.step(x, u, rng.uniform(-W_BOUND, W_BOUND, 2))
    return np.array(us), infos


def _starts() -> list[np.ndarray]:
    return [np.asarray(unstable2d_setup(N).x0, dtype=float),
            *np.random.default_rng(5).uniform([-0.8, -5.0], [0.8, 5.0], (2, 2))]


def test_ordinary_steps_start_from_the_candidate_with_the_previous_multipliers() -> None:
    """The first attempt of an ordinary (6.15) gets the candidate's primal point (as the
    backend packs the candidate dict) and the previous converged (6.15)'s multipliers,
    checked at the solver call; before the first converged (6.15) zero multipliers."""
    ctrl = _controller()
    prob = ctrl.problem
    seen: list = []
    solve_with = CasadiCompiled._solve_with

    def spy(self, solver, p, guess):
        if self is prob:
            seen.append(guess)
        return solve_with(self, solver, p, guess)

    ctrl.reset()
    x, rng, ordinary = _starts()[0], np.random.default_rng(0), 0
    CasadiCompiled._solve_with = spy
    try:
        for _ in range(STEPS):
            seen.clear()
            cand, last = ctrl.candidate, ctrl._last
            plain = last is not None and not ctrl._recovered
            u, info = ctrl.step(x, np.array([2.5]))
            w, lam_x, lam_g = seen[0]
            p = prob.ocp.pack_parameters({"x0": x, "u_p": np.array([2.5]),
                                          "bound": info.values["bound"]})
            want = prob._initial_guess(ctrl._candidate_start(cand), p)[0] if cand is not None \
                else None
            if plain:
                assert isinstance(last, Solution) and last.success
                assert np.array_equal(np.asarray(w, dtype=float).ravel(),
                                      np.asarray(want, dtype=float).ravel())
                assert np.array_equal(np.asarray(lam_x, dtype=float),
                                      np.asarray(last.raw["dm"][1], dtype=float))
                assert np.array_equal(np.asarray(lam_g, dtype=float),
                                      np.asarray(last.raw["dm"][2], dtype=float))
                assert np.any(np.asarray(lam_g, dtype=float) != 0)
                ordinary += 1
            x = ctrl.system.step(x, u, rng.uniform(-W_BOUND, W_BOUND, 2))
    finally:
        CasadiCompiled._solve_with = solve_with
    assert ordinary >= 10, ordinary


def test_off_starts_from_the_previous_solution() -> None:
    """``candidate_duals=False`` (the default) starts the ordinary (6.15) from the previous
    converged (6.15) itself: the two starts give different loops (so the C test below can
    tell them apart)."""
    on, off = _controller(True), _controller(False)
    a, _ = _loop(on, _starts()[0], 0)
    b, _ = _loop(off, _starts()[0], 0)
    # (6.15) is not unique (docs/vehicles.md, session 13): other starts, other loops
    assert not np.array_equal(a, b)


def test_candidate_duals_must_be_a_bool() -> None:
    robust, system = _design()
    s = unstable2d_setup(N)
    with pytest.raises(BalustradeError, match="candidate_duals"):
        MultiobjectivePCBFController.build(
            system, s.X, s.U, robust.h_f, robust.pi_f, N, s.deltas(), robust.error,
            s.alpha_f, rho=0.5, target=EMITTABLE_TARGET, slack_target=EMITTABLE_TARGET,
            candidate_duals="yes")


def test_both_candidate_options_are_refused_before_compiling(monkeypatch) -> None:
    """candidate_duals already starts every ordinary (6.15) from the candidate, so with
    candidate_second as well the second would never run (review R2, session 14)."""
    robust, system = _design()
    s = unstable2d_setup(N)
    import balustrade.control.multiobjective as mo

    def no_compile(*args, **kwargs):
        raise AssertionError("compiled before the options were checked")
    monkeypatch.setattr(mo, "compile", no_compile, raising=False)
    with pytest.raises(BalustradeError, match="exclude each other"):
        MultiobjectivePCBFController.build(
            system, s.X, s.U, robust.h_f, robust.pi_f, N, s.deltas(), robust.error,
            s.alpha_f, rho=0.5, target=EMITTABLE_TARGET, slack_target=EMITTABLE_TARGET,
            candidate_duals=True, candidate_second=True)


def test_candidate_second_runs_after_a_failed_first_attempt() -> None:
    """With the capped SQP, failed first attempts of ordinary (6.15) are followed by an
    attempt from the candidate with the previous (6.15)'s multipliers (checked at the
    solver call), and the loop differs from the one without it."""
    ctrl = _controller(False, True)
    prob = ctrl.problem
    seen: list = []
    solve_with = CasadiCompiled._solve_with

    def spy(self, solver, p, guess):
        sol = solve_with(self, solver, p, guess)
        if self is prob:
            seen.append((guess, sol.success))
        return sol

    second = 0
    CasadiCompiled._solve_with = spy
    try:
        for j, x0 in enumerate(_starts()):
            ctrl.reset()
            x, rng = x0, np.random.default_rng(j)
            for _ in range(STEPS):
                seen.clear()
                cand, last = ctrl.candidate, ctrl._last
                plain = last is not None and not ctrl._recovered
                u, info = ctrl.step(x, np.array([2.5]))
                if plain and not seen[0][1]:
                    (w, lam_x, lam_g), _ = seen[1]
                    p = prob.ocp.pack_parameters({"x0": x, "u_p": np.array([2.5]),
                                                  "bound": info.values["bound"]})
                    want = prob._initial_guess(ctrl._candidate_start(cand), p)[0]
                    assert np.array_equal(np.asarray(w, dtype=float).ravel(),
                                          np.asarray(want, dtype=float).ravel())
                    assert np.array_equal(np.asarray(lam_x, dtype=float),
                                          np.asarray(last.raw["dm"][1], dtype=float))
                    assert np.array_equal(np.asarray(lam_g, dtype=float),
                                          np.asarray(last.raw["dm"][2], dtype=float))
                    second += 1
                x = ctrl.system.step(x, u, rng.uniform(-W_BOUND, W_BOUND, 2))
    finally:
        CasadiCompiled._solve_with = solve_with
    assert second >= 3, second
    loops = [np.concatenate([_loop(_controller(False, on, capped=True), x0, j)[0]
                             for j, x0 in enumerate(_starts())]) for on in (True, False)]
    assert not np.array_equal(*loops)


@pytest.mark.parametrize("option", ["candidate_duals", "candidate_second"])
def test_c_equals_python_bitwise_with_candidate_starts(tmp_path, option: str) -> None:
    """The emitted C starts its ordinary (6.15) the same way: free-running loops from three
    starts, inputs, statuses, fallbacks and recorded values equal to the last bit (fails
    with ``<name>_CANDIDATE_DUALS`` 0 in the C)."""
    py = _controller(option == "candidate_duals", option == "candidate_second")
    c = accelerate(py, build_dir=tmp_path, name="mocd")
    for j, x0 in enumerate(_starts()):
        (ua, ia), (ub, ib) = _loop(py, x0, j), _loop(c, x0, j, py.system)
        assert np.array_equal(ua, ub), (j, np.max(np.abs(ua - ub)))
        for k, (i1, i2) in enumerate(zip(ia, ib)):
            assert (_kind(i1.status), i1.fallback) == (_kind(i2.status), i2.fallback), (j, k)
            for key in set(i1.values) & set(i2.values):
                v1, v2 = i1.values[key], i2.values[key]
                assert v1 == v2 or (np.isnan(v1) and np.isnan(v2)), (j, k, key, v1, v2)
