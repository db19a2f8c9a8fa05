"""C = Python *bitwise* along the closed loops of Algorithms 5.2 and 6.4 (issue #14, issue #16
§8.2; docs/vehicles.md, "Session 13: C = Python along loops").

Session 13 traced the first differing bit between the Python controllers and their emitted C
on the lane change: every solve (the SQP attempts, their QPs, the interior-point retry)
returned bitwise the same point from the same data; what differed were the numbers between
the solves — ``h̃`` summed pairwise by numpy and left to right by the C, ``d·P·d`` of ``h_f``
and ``K e`` of the applied input through BLAS. One rounding (2.2e-16) at step 0 or 1 grew to
1e-8 and, where attempts of the retry chain answer at nearby states, to 4.9e-3 (session 12:
9 of 16 seeds of Algorithm 6.4 beyond 1e-6). Now Python evaluates the CasADi functions the
C is generated from (:mod:`balustrade.control.tube_functions`) and ``K e`` is summed in the
C's order (:meth:`~balustrade.dsl.error_sets.ErrorSet.kappa`, ``bal/tube_common.c``), and
the loops are equal to the last bit. These tests fail when any of those orders changes
on one side only."""

from __future__ import annotations

import numpy as np
import pytest
from test_emit_robust import HIGH, LOW, _design, _kind

from balustrade.codegen import accelerate
from balustrade.codegen.emit_robust import EMITTABLE_TARGET
from balustrade.control.multiobjective import MultiobjectivePCBFController
from balustrade.control.robust_steps import polished_slacks, robust_candidate, slack_cost
from balustrade.control.tube_functions import TubeFunctions
from balustrade.dsl.error_sets import ErrorSet
from balustrade.dsl.sets import Box
from balustrade.models.unstable2d import W_BOUND, unstable2d_setup

N = 10


def _left_to_right(K: np.ndarray, e: np.ndarray) -> np.ndarray:
    """``K e`` with Python floats, each row summed from its first term (the C's order)."""
    out = []
    for row in K:
        acc = float(row[0]) * float(e[0])
        for k, e_k in zip(row[1:], e[1:]):
            acc += float(k) * float(e_k)
        out.append(acc)
    return np.array(out)


def test_kappa_sums_left_to_right() -> None:
    rng = np.random.default_rng(0)
    for nu, nx in ((1, 2), (2, 4), (3, 7), (2, 16)):
        err = ErrorSet(Box(-np.ones(nx), np.ones(nx)), K=rng.standard_normal((nu, nx)))
        for _ in range(50):
            e = rng.standard_normal(nx) * 10.0 ** rng.integers(-8, 3)
            got = err.kappa(e)
            assert np.array_equal(got, _left_to_right(err.K, e)), (nu, nx, got)


@pytest.fixture(scope="module")
def loops(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """Algorithms 5.2 and 6.4 on the 2-D example of Section 5.6 (N = 10), the Python
    controllers with the backend's whole chain (no mirror) and their C through accelerate."""
    robust, system = _design()
    s = unstable2d_setup(N)
    mo = MultiobjectivePCBFController.build(
        system, s.X, s.U, robust.h_f, robust.pi_f, N, s.deltas(), robust.error, s.alpha_f,
        rho=0.5, target=EMITTABLE_TARGET, slack_target=EMITTABLE_TARGET)
    ctrls = {"robust": robust, "multiobjective": mo}
    return {"py": ctrls, "system": system,
            "c": {k: accelerate(v, build_dir=tmp_path_factory.mktemp(k))
                  for k, v in ctrls.items()}}


def test_tube_functions_compute_what_the_numpy_path_does(loops: dict) -> None:
    """The CasADi path is the same algorithm as :mod:`~balustrade.control.robust_steps`
    (values to 1e-12), only rounded in the C's order."""
    py = loops["py"]["robust"]
    tube = py._tube
    assert isinstance(tube, TubeFunctions)
    rng = np.random.default_rng(1)
    checked = 0
    for x in rng.uniform(LOW, HIGH, (8, 2)):
        s = py.slack.solve({"x0": x})
        if not s.success:
            continue
        xi, xi_N = tube.polish(s)
        xi_np, xi_N_np = polished_slacks(s, py.X_E, py.h_f, py.deltas)
        assert np.allclose(xi, xi_np, rtol=1e-12, atol=1e-14) and \
            abs(xi_N - xi_N_np) <= 1e-12 * max(1.0, abs(xi_N_np))
        h, h_np = tube.cost(xi, xi_N), slack_cost(xi_np, xi_N_np, py.alpha_f, py.slack_norm)
        assert abs(h - h_np) <= 1e-12 * max(1.0, abs(h_np))
        cand = tube.candidate(s["z"], s["v"], xi)
        ref = robust_candidate(py.system, py.X_E, py.h_f, py.pi_f, py.deltas, s["z"], s["v"],
                               xi, py.U_E)
        if cand is None:      # terminal input outside U ⊖ κ(E) without a closed form
            continue
        for a, b in ((cand.z, ref.z), (cand.v, ref.v), (cand.xi, ref.xi)):
            assert np.allclose(a, b, rtol=1e-9, atol=1e-9)
        checked += 1
    assert checked >= 4, checked


def _loop(ctrl: object, system: object, x0: np.ndarray, steps: int, rng_seed: int) -> dict:
    rng = np.random.default_rng(rng_seed)
    ctrl.reset()
    x, us, infos = np.asarray(x0, dtype=float), [], []
    for _ in range(steps):
        u, info = ctrl.step(x, np.array([2.5]))
        us.append(np.array(u))
        infos.append(info)
        x = system.step(x, u, rng.uniform(-W_BOUND, W_BOUND, 2))
    return {"u": np.array(us), "infos": infos}


@pytest.mark.parametrize("kind", ["robust", "multiobjective"])
def test_c_equals_python_bitwise_along_closed_loops(loops: dict, kind: str) -> None:
    """Free-running loops (each side on its own states) from x_0 of Section 5.6 and from
    random states, under seeded disturbances: inputs, statuses, fallbacks and the recorded
    values (h_r, h_cand, bound, h̃) equal to the last bit (statuses up to the words the C
    cannot tell apart: ``not_converged`` for ``failed`` / ``max_iterations``)."""
    py, c, system = loops["py"][kind], loops["c"][kind], loops["system"]
    starts = [unstable2d_setup(N).x0,
              *np.random.default_rng(5).uniform([-0.8, -5.0], [0.8, 5.0], (3, 2))]
    nonzero_slacks = 0
    for j, x0 in enumerate(starts):
        a, b = _loop(py, system, x0, 20, j), _loop(c, system, x0, 20, j)
        assert np.array_equal(a["u"], b["u"]), (kind, j, np.max(np.abs(a["u"] - b["u"])))
        for k, (i1, i2) in enumerate(zip(a["infos"], b["infos"])):
            # the C cannot tell why a solve did not converge (test_emit_robust._kind)
            assert (_kind(i1.status), i1.fallback) == (_kind(i2.status), i2.fallback), \
                (kind, j, k, i1.status, i2.status)
            for key in set(i1.values) & set(i2.values):
                v1, v2 = i1.values[key], i2.values[key]
                assert v1 == v2 or (np.isnan(v1) and np.isnan(v2)), (kind, j, k, key, v1, v2)
            h = i1.values.get("h_r", i1.values.get("h_tilde", 0.0))
            nonzero_slacks += bool(np.isfinite(h) and h > 0)
    assert nonzero_slacks >= 5, nonzero_slacks   # the polish and h̃ sums are exercised


@pytest.mark.slow
@pytest.mark.parametrize(("kind", "seed"), [("robust", 1), ("multiobjective", 1),
                                            ("robust", 8)])
def test_lane_change_c_equals_python_bitwise(kind: str, seed: int) -> None:
    """The lane change (``converging``), 60 steps. Seed 1: before session 13 the C and
    Python differed from step 0 (6.4) / step 4 (5.2), Algorithm 6.4 by 3.9e-3 from step
    165. Seed 8 (5.2): at step 1 Python's IPOPT retry of (5.16) stopped at its acceptable
    level and the C's did not (2.6e-8 along the loop; fails without
    ``casadi_backend.EMITTED_STOP_OPTIONS``). Now the loops are bitwise equal."""
    from balustrade.reproduce import lane_change as L

    cfg = L.config("converging")
    d = L.design(cfg)
    py = L.controllers(d, rho=cfg.rho)[kind]
    ws = L.disturbances(d, seed, 60)
    a, b = L.closed_loop(py, d, ws), L.closed_loop(accelerate(py), d, ws)
    assert np.array_equal(a["inputs"], b["inputs"]), np.max(np.abs(a["inputs"] - b["inputs"]))
    assert np.array_equal(a["states"], b["states"])
    assert a["fallbacks"] == b["fallbacks"]
    # the same words, IPOPT's own Solved_To_Acceptable_Level included (seed 8, step 1:
    # "filter_optimal_inaccurate" in both; the C reads it from IPOPT's return status,
    # <P>_inaccurate: tests/test_ipopt_status.py)
    assert a["statuses"] == b["statuses"]


def test_emitted_targets_retry_with_the_stopping_rule_of_their_c(loops: dict) -> None:
    """The IPOPT retry of an as-emitted target (``robust-sqp``) never stops at its
    acceptable level, as its emitted C (``emittable.STATUS_OPTIONS``); a target that is not
    emitted keeps IPOPT's defaults."""
    from balustrade.backends.casadi_backend import EMITTED_STOP_OPTIONS
    from balustrade.backends.emittable import STATUS_OPTIONS

    slack = loops["py"]["robust"].slack
    assert slack.as_emitted and [n for n, _ in slack.retries][-1] == "ipopt"
    opts = slack._retry_options("ipopt", {})
    assert opts["ipopt.acceptable_iter"] == 0
    assert EMITTED_STOP_OPTIONS["ipopt"].items() <= STATUS_OPTIONS["ipopt"].items()
    plain = slack.with_retries(slack.retries)
    plain.as_emitted = False
    assert "ipopt.acceptable_iter" not in plain._retry_options("ipopt", {})


def test_every_build_turns_off_fused_multiply_add() -> None:
    """CasADi's evaluation in Python rounds each operation; a C compiled with contraction
    (GCC's default where the target has FMA: ``-march=native``, aarch64) would not, so the
    library build, the example executable and the generated Makefile all pass
    ``-ffp-contract=off`` (x86-64 without ``-march`` has no FMA: the loops above are
    bitwise equal with or without it on this machine)."""
    import importlib
    import inspect
    from importlib.resources import files

    B = importlib.import_module("balustrade.codegen.build")

    assert "-ffp-contract=off" in B.BASE_FLAGS
    assert "FP_FLAGS" in inspect.getsource(B.build_executable)
    makefile = files("balustrade.codegen").joinpath("c/Makefile.in").read_text()
    assert "-ffp-contract=off" in makefile


def compare_seeds(seeds: list[int], kinds: tuple[str, ...] = ("robust", "multiobjective"),
                  steps: int = 200) -> dict:
    """The session-13 measurement: per seed and algorithm, the lane change's free-running
    closed loops in Python and in C (``converging``), compared by
    :func:`~balustrade.reproduce.lane_change.compare`, plus the first step whose inputs
    differ at all (-1: none)."""
    from balustrade.reproduce import lane_change as L

    cfg = L.config("converging")
    d = L.design(cfg)
    ctrls = L.controllers(d, rho=cfg.rho)
    cs = {k: accelerate(ctrls[k]) for k in kinds}
    rows = {}
    for seed in seeds:
        ws = L.disturbances(d, seed, steps)
        for kind in kinds:
            py, c = L.closed_loop(ctrls[kind], d, ws), L.closed_loop(cs[kind], d, ws)
            row = L.compare(py, c)
            nonzero = np.flatnonzero(np.max(np.abs(py["inputs"] - c["inputs"]), axis=1) > 0)
            row["first_step_nonzero"] = int(nonzero[0]) if nonzero.size else -1
            rows[f"{kind}/{seed}"] = row
            print(kind, seed, row, flush=True)
    return rows


if __name__ == "__main__":   # PYTHONPATH=$PWD python tests/test_lane_sync.py 0,1,2 [steps]
    import sys

    compare_seeds([int(s) for s in sys.argv[1].split(",")],
                  steps=int(sys.argv[2]) if len(sys.argv) > 2 else 200)
