"""RAPSF's default target ``fast-convex-sized`` (issue #15, session 14): the direct backend
picks the hot-started DAQP engine when the lowered (4.5) is small (at most
``SIZED_DENSE_LIMIT`` dense constraint entries) and PIQP otherwise; on the 3-mass design of
``reproduce msd-adaptive`` (SPEC §3.2) the default runs DAQP and applies the inputs of an
explicit ``fast-convex`` (PIQP) loop, with (x, u) ∈ 𝒵 at every step; on 8 masses it runs row
generation on PIQP. The engine chosen is checked, never a time."""

from __future__ import annotations

import numpy as np
import pytest

from balustrade.backends import compile
from balustrade.backends.daqp_engine import DENSE_LIMIT
from balustrade.backends.targets import PRESETS, SIZED_DENSE_LIMIT, Target
from balustrade.control.rapsf import DEFAULT_TARGET, RAPSF
from balustrade.errors import SolverError

pytest.importorskip("daqp")

STEPS = 30


@pytest.fixture(scope="module")
def msd3():
    from balustrade.reproduce import msd_adaptive
    return msd_adaptive.design(3)


def _controller(d: dict, **kw: object) -> RAPSF:
    from balustrade.reproduce import msd_adaptive
    s = d["setup"]
    return RAPSF(d["system"], d["X0"], msd_adaptive.joint(d), None, s.W, d["K"], s.N,
                 s.Theta0, estimator=msd_adaptive.BoxUpdate(d["system"], s.W, s.Theta0),
                 **kw)


def test_the_preset_limit_is_the_engines_own() -> None:
    """The default hands DAQP nothing the engine itself would refuse."""
    assert SIZED_DENSE_LIMIT == DENSE_LIMIT
    assert DEFAULT_TARGET == "fast-convex-sized" and DEFAULT_TARGET in PRESETS


def test_default_three_masses_runs_daqp_with_the_inputs_of_piqp(msd3) -> None:
    """30 closed-loop steps (θ*, disturbances of seed 0, the aggressive proposal of the
    reproduction) of the default controller and of ``target="fast-convex"`` side by side:
    the default's (4.5) is solved by DAQP, its inputs equal PIQP's within 1e-6 and every
    (x_k, u_k) lies in 𝒵 = {Fx + Gu <= 1}."""
    from balustrade.reproduce import msd_adaptive
    from benchmarks.bench_rapsf import Loop

    default, piqp = _controller(msd3), _controller(msd3, target="fast-convex")
    assert default.engine is None
    runs = {"default": Loop(msd3, default.step, STEPS), "piqp": Loop(msd3, piqp.step, STEPS)}
    Z = msd_adaptive.joint(msd3)
    F, G = Z.F, Z.G
    for k in range(STEPS):
        for loop in runs.values():
            x = loop.x.copy()
            loop(k)
            u = loop.applied[-1]
            assert np.max(F @ x + G @ u) <= 1 + 1e-7, (k, np.max(F @ x + G @ u))
        ua, ub = runs["default"].applied[-1], runs["piqp"].applied[-1]
        assert np.max(np.abs(ua - ub)) <= 1e-6, (k, ua, ub)
        assert default.engine == "daqp" and piqp.engine == "piqp", (default.engine,
                                                                    piqp.engine)
    assert runs["default"].fallbacks == runs["piqp"].fallbacks


def test_size_rule_direction_on_the_three_mass_problem(msd3) -> None:
    """At a limit equal to the lowered (4.5)'s ``m · n`` DAQP is chosen, one entry below it
    PIQP: the rule hands DAQP the small problems, not the large ones."""
    ctrl = _controller(msd3)
    _, info = ctrl.step(msd3["setup"].x0, np.zeros(3))
    assert info.solutions["rapsf"].solver == "daqp"
    (compiled,) = [c for c in ctrl._compiled.values() if c.ocp.N == ctrl.N]
    m, n = compiled.program.A.shape
    assert compiled.program.large is None and compiled.solver_name == "daqp"
    at = compile(compiled.ocp, Target("direct", None, {"daqp_max_entries": m * n}))
    below = compile(compiled.ocp, Target("direct", None, {"daqp_max_entries": m * n - 1}))
    assert at.solver_name == "daqp" and below.solver_name == "piqp"
    p = {"x0": msd3["setup"].x0, "u_p": np.zeros(3), "theta": ctrl.vertices.T,
         "s": ctrl._s}
    sa, sb = at.solve(p), below.solve(p)
    assert sa.solver == "daqp" and sb.solver == "piqp"
    assert abs(sa.objective - sb.objective) <= 1e-6 * (1 + abs(sb.objective))


@pytest.mark.parametrize("bad", [0, -5, 1.5, True, "big"])
def test_bad_limit_is_refused_by_name(msd3, bad) -> None:
    ctrl = _controller(msd3, target=Target("direct", None, {"daqp_max_entries": bad}))
    with pytest.raises(SolverError, match="daqp_max_entries"):
        ctrl.step(msd3["setup"].x0, np.zeros(3))


def test_limit_with_a_named_solver_is_refused(msd3) -> None:
    ctrl = _controller(msd3, target=Target("direct", "piqp", {"daqp_max_entries": 10}))
    with pytest.raises(SolverError, match="daqp_max_entries"):
        ctrl.step(msd3["setup"].x0, np.zeros(3))


@pytest.mark.slow
def test_default_eight_masses_runs_row_generation_on_piqp() -> None:
    """8 masses (28644 tube rows): the default compiles (4.5) for row generation, whose
    engine is PIQP — DAQP was 4x slower there (docs/adaptive.md, session 14)."""
    from balustrade.reproduce import msd_adaptive

    d = msd_adaptive.design(8)
    ctrl = _controller(d)
    u, info = ctrl.step(d["setup"].x0, np.zeros(8))
    assert ctrl.engine == "piqp" and info.solutions["rapsf"].solver == "piqp"
    (compiled,) = [c for c in ctrl._compiled.values() if c.ocp.N == ctrl.N]
    assert compiled.rowgen is not None
    m, n = compiled.program.A.shape
    assert m * n > SIZED_DENSE_LIMIT


def test_default_is_emitted_hot_and_refuses_what_that_c_does_not_run(msd3, tmp_path) -> None:
    """Since session 15 the default 3-mass RAPSF is emitted with (4.5) hot-started in C
    (``bal/rapsf_hot.c``; C = Python in tests/test_rapsf_hot_c.py); Remark 4.6 and a user
    backup are refused there, naming ``convex-qp``, before anything is written."""
    from balustrade.codegen.emit_rapsf import emit_rapsf
    from balustrade.errors import BalustradeError

    for kw in ({"shrinking": True}, {"backup": (np.zeros((3, 6)), np.zeros(3))}):
        with pytest.raises(BalustradeError, match="convex-qp"):
            emit_rapsf(_controller(msd3, **kw), "r", tmp_path)
        assert not list(tmp_path.iterdir())
    em = emit_rapsf(_controller(msd3), "r", tmp_path)
    assert em.manifest["qp"] == "hot" and em.libraries == ("daqp",)
