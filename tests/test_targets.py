"""Solver targets as data (issue #13 §1): presets, immutability, pickling, emit_reason, and
``target=`` through compile and every controller builder."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from balustrade.backends import (
    PRESETS,
    Target,
    companion,
    compile,
    resolve_target,
    sampling_targets,
)
from balustrade.backends.targets import ALIASES, SAMPLING_PAIRS
from balustrade.control.approximate import ApproximatePCBFFilter
from balustrade.control.multiobjective import (
    MultiobjectiveLyapunovController,
    MultiobjectivePCBFController,
)
from balustrade.control.pcbf import PCBFSafetyFilter
from balustrade.control.robust import RobustPCBFSafetyFilter
from balustrade.dsl import OCP, Box, FunctionSet, LinearSystem, squared_norm
from balustrade.errors import BalustradeError, SolverError


def _small_ocp() -> OCP:
    sys_ = LinearSystem(np.array([[1.0, 0.1], [0.0, 1.0]]), np.array([[0.0], [0.1]]))
    ocp = OCP(sys_, 3, name="small")
    ocp.initial_state(ocp.parameter("x0", 2))
    ocp.dynamics()
    ocp.input_constraint(Box([-1.0], [1.0]))
    ocp.minimize(squared_norm(ocp.x) + squared_norm(ocp.u))
    return ocp


# -- presets -------------------------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(PRESETS))
def test_every_preset_resolves_to_itself(name):
    t = resolve_target(name)
    assert t is PRESETS[name] and t.name == name
    assert t.backend in ("casadi", "cvxpy", "direct", "auto")


def test_aliases_and_backend_names_resolve():
    for old, new in ALIASES.items():
        assert resolve_target(old) is PRESETS[new]
    assert resolve_target("casadi") is PRESETS["exact"]
    assert resolve_target("cvxpy") is PRESETS["cvxpy"]
    assert resolve_target(None) is PRESETS["exact"]
    assert resolve_target(None, default="fast-sqp") is PRESETS["fast-sqp"]


def test_unknown_preset_error_lists_presets():
    with pytest.raises(SolverError, match=r"unknown backend 'fastest' \(nor a target preset\)"
                       ) as exc:
        resolve_target("fastest")
    for name in PRESETS:
        assert name in str(exc.value)
    with pytest.raises(SolverError, match="expected a Target"):
        resolve_target(3)


def test_preset_options_are_the_documented_ones():
    assert PRESETS["robust-sqp"].options["max_iter"] == 500
    assert PRESETS["fast-sqp-noretry"].retries == ()
    warm, cold = PRESETS["sampling-warm"], PRESETS["sampling-cold"]
    assert dict(cold.options).items() <= dict(warm.options).items()
    assert len(warm.options) > len(cold.options)


# -- immutability --------------------------------------------------------------------------
def test_targets_are_immutable_and_with_returns_copies():
    t = PRESETS["fast-sqp"]
    before = (t.solver, dict(t.options), t.retries, t.name)
    with pytest.raises(AttributeError):
        t.solver = "other"  # type: ignore[misc]
    with pytest.raises(TypeError):
        t.options["max_iter"] = 3  # type: ignore[index]
    a = t.with_options(max_iter=7)
    b = t.with_retries(())
    c = t.with_solver(PRESETS["exact"].solver)
    assert a is not t and a.options["max_iter"] == 7
    assert b is not t and b.retries == ()
    assert c is not t and c.solver == PRESETS["exact"].solver
    assert (t.solver, dict(t.options), t.retries, t.name) == before
    # the plain copies handed to the backends are the caller's to change
    opts = a.solver_options()
    opts["max_iter"] = 1
    assert a.options["max_iter"] == 7


def test_target_with_options_and_retries_override():
    t = resolve_target("fast-sqp", options={"max_iter": 3}, retries=[])
    assert t.options["max_iter"] == 3 and t.retries == () and t.solver == "sqpmethod"


# -- pickling ------------------------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(PRESETS))
def test_targets_pickle_round_trip(name):
    t = PRESETS[name].with_options({"nested": {"a": 1}})
    u = pickle.loads(pickle.dumps(t))
    assert u == t and dict(u.options) == dict(t.options) and u.name == t.name
    assert u.retry_chain() == t.retry_chain()
    with pytest.raises(TypeError):
        u.options["x"] = 1  # type: ignore[index]


def test_target_with_retries_pickles():
    t = PRESETS["fast-sqp"].with_retries([("sqpmethod", {"convexify_strategy": "eigen-reflect"})])
    u = pickle.loads(pickle.dumps(t))
    assert u.retry_chain() == [("sqpmethod", {"convexify_strategy": "eigen-reflect"})]


# -- companions and sampling pairs ---------------------------------------------------------
def test_companion_follows_the_backend():
    assert companion(None, "robust-sqp") is PRESETS["exact"]
    assert companion(None, "cvxpy") is PRESETS["cvxpy"]
    assert companion("long-horizon", "cvxpy") is PRESETS["long-horizon"]


def test_sampling_targets():
    for name, (warm, cold) in SAMPLING_PAIRS.items():
        assert sampling_targets(name) == (PRESETS[warm], PRESETS[cold])
    assert sampling_targets("exact-ipopt") == sampling_targets("exact")  # an alias
    assert sampling_targets("robust-sqp") == (PRESETS["robust-sqp"], None)


# -- emit_reason ---------------------------------------------------------------------------
def test_emit_reason():
    assert PRESETS["fast-sqp"].emit_reason() is None and PRESETS["fast-sqp"].can_emit
    assert PRESETS["robust-sqp"].can_emit
    assert "CasADi" in PRESETS["cvxpy"].emit_reason()
    reason = PRESETS["exact"].emit_reason()
    assert reason is not None and "'exact'" in reason and "fast-sqp" in reason
    qp = PRESETS["fast-sqp"].with_options(qpsol="qpoases")
    assert "qpoases" in qp.emit_reason()
    ext = PRESETS["fast-sqp"].with_options(qpsol="osqp")
    assert "libosqp" in ext.emit_reason() and ext.emit_reason(allow_external=True) is None
    assert ext.c_libraries() == ("osqp",) and PRESETS["fast-sqp"].c_libraries() == ()
    assert Target("casadi").nlp_solver == PRESETS["exact"].solver


# -- compile records the target ------------------------------------------------------------
def test_compile_records_target_and_with_retries_copies():
    ocp = _small_ocp()
    c = compile(ocp, "fast-sqp")
    assert c.target is PRESETS["fast-sqp"] and c.solver_name == "sqpmethod"
    retries, tgt = list(c.retries), c.target
    d = c.with_retries([])
    assert d is not c and d.retries == [] and d.target.retries == ()
    assert c.retries == retries and c.target is tgt  # the original is unchanged
    assert d.solve({"x0": [0.5, 0.0]}).success
    e = compile(ocp, "cvxpy")
    assert e.target is PRESETS["cvxpy"]
    f = compile(ocp, "robust-sqp")
    assert f.options["max_iter"] == 500


def test_compile_rejects_unknown_targets_naming_the_problem():
    with pytest.raises(SolverError, match="small: unknown backend 'nope'"):
        compile(_small_ocp(), "nope")


# -- target="cvxpy" through every controller builder ------------------------------------------
def _backends(*compiled) -> set[str]:
    return {c.target.backend for c in compiled}


def test_pcbf_builder_takes_targets(pend):
    p = pend
    args = (p.system, p.X, p.U, p.h_f, p.N, p.deltas, p.alpha_f)
    cv = PCBFSafetyFilter.build(*args, slack_norm=1, target="cvxpy")
    assert _backends(cv.slack, cv.filter) == {"cvxpy"}
    sq = PCBFSafetyFilter.build(*args, slack_norm=1)
    assert sq.slack.target is PRESETS["fast-sqp"] and sq.filter.target is PRESETS["fast-sqp"]
    u, info = cv.step(np.array([0.1, 0.0]), np.array([0.0]))
    assert info.status == "ok" and np.all(np.isfinite(u))


def test_robust_and_multiobjective_builders_take_targets(unstable2d_tube):
    t = unstable2d_tube
    system, s, error, cbf, N = t["system"], t["s"], t["error"], t["cbf"], t["N"]
    args = (system, s.X, s.U, cbf, cbf.policy, N, s.deltas(), error, s.alpha_f)
    r = RobustPCBFSafetyFilter.build(*args, target="cvxpy")
    assert _backends(r.slack, r.filter) == {"cvxpy"}
    r = RobustPCBFSafetyFilter.build(*args)  # "auto": a convex problem goes direct
    assert r.filter.target is r.slack.target is PRESETS["fast-convex"]
    r = RobustPCBFSafetyFilter.build(*args, target="robust-sqp")
    assert r.filter.target is PRESETS["robust-sqp"] and r.slack.target is PRESETS["exact"]
    r = RobustPCBFSafetyFilter.build(*args, target="long-horizon", slack_target="long-horizon")
    assert r.slack.target is r.filter.target is PRESETS["long-horizon"]
    m = MultiobjectivePCBFController.build(*args, target="cvxpy")
    assert _backends(m.slack, m.problem) == {"cvxpy"}
    m = MultiobjectivePCBFController.build(*args)
    assert m.slack.target is m.problem.target is PRESETS["fast-convex"]
    m = MultiobjectivePCBFController.build(*args, target="exact")
    assert m.slack.target is m.problem.target is PRESETS["exact"]


def test_lyapunov_builder_takes_targets(unstable2d_tube):
    from balustrade.dsl.error_sets import minimal_rpi_outer
    from balustrade.problems.multiobjective import LinearLyapunovDesign

    t = unstable2d_tube
    system, s, error = t["system"], t["s"], t["error"]
    Xf = minimal_rpi_outer(system.A + system.B @ error.K, s.W, 1e-4).polytope().scale(3.0)
    des = LinearLyapunovDesign(system, s.X, s.U, Xf, s.W, error.K, np.eye(2), np.eye(1), 5)
    ctl = MultiobjectiveLyapunovController.build(des, target="cvxpy")
    assert _backends(ctl.problem, ctl.init) == {"cvxpy"}
    ctl = MultiobjectiveLyapunovController.build(des)
    assert ctl.problem.target is PRESETS["exact"]


def test_approximate_filter_takes_casadi_targets(pend):
    p = pend
    f = ApproximatePCBFFilter(p.system, p.U, p.h_f, target="fast-sqp")
    assert f.filter.target is PRESETS["fast-sqp"] and f.decrease.compiled.solver_name == "sqpmethod"
    with pytest.raises(BalustradeError, match="need a CasADi target"):
        ApproximatePCBFFilter(p.system, p.U, p.h_f, target="cvxpy")


# -- FunctionSet.support comes from the backends -------------------------------------------
def test_function_set_support_solver_is_registered_or_given():
    disk = FunctionSet(lambda x: x[0] ** 2 + x[1] ** 2 - 1.0, 2, name="disk")
    assert disk.support(np.array([1.0, 0.0])) == pytest.approx(1.0, abs=1e-6)
    own = FunctionSet(lambda x: x[0] ** 2 + x[1] ** 2 - 1.0, 2, name="disk",
                      support=lambda fs, a: 42.0)
    assert own.support(np.array([1.0, 0.0])) == 42.0
    assert own.scale(2.0).support(np.array([1.0, 0.0])) == 42.0  # kept by derived sets


def test_function_set_without_support_solver_says_so(monkeypatch):
    from balustrade.dsl import sets_function

    monkeypatch.setattr(sets_function, "_DEFAULT_SUPPORT", [])
    disk = FunctionSet(lambda x: x[0] ** 2 + x[1] ** 2 - 1.0, 2, name="disk")
    with pytest.raises(BalustradeError, match="disk.support: no support solver"):
        disk.support(np.array([1.0, 0.0]))


def test_is_preset_compares_every_field_not_only_the_name():
    """``Target.is_preset``: the presets (and their aliases) are; a copy with other options,
    retries or a budget is not, although ``==`` (options, retries, budget left out) and the
    name say otherwise; a custom target is not."""
    from dataclasses import replace

    for name, t in PRESETS.items():
        assert t.is_preset(), name
    assert resolve_target("clarabel").is_preset()  # an alias resolves to the preset itself
    fc = PRESETS["fast-convex"]
    for other in (replace(fc, options={"eps_abs": 1e-6}),
                  replace(PRESETS["exact"], retries=()),
                  replace(PRESETS["fast-sqp"].with_budget(iterations=2), name="fast-sqp")):
        assert not other.is_preset(), other
    assert replace(fc, options={"eps_abs": 1e-6}) == fc  # why == cannot decide it
    assert not Target("casadi", "ipopt").is_preset()


def test_every_emitted_preset_retries_with_the_stopping_rule_of_its_c():
    """Every CasADi preset whose C the emitters generate (its first solver emittable, a
    library allowed) compiles ``as_emitted``: its IPOPT retry stops as the emitted IPOPT
    does (``acceptable_iter`` 0, ``emittable.STATUS_OPTIONS``), ``structured-ip`` included
    (session 13 review: it carried no lowering option, so Python's IPOPT retry kept
    IPOPT's acceptable stop while the C has none). The IPOPT-first presets are not
    emitted as closed-loop C (their first attempt is the known gap, not a retry)."""
    from balustrade.backends.casadi_backend import EMITTED_STOP_OPTIONS

    emitted = [n for n, t in PRESETS.items() if t.backend == "casadi"
               and t.nlp_solver != "ipopt" and t.emit_reason(allow_external=True) is None]
    assert {"structured-ip", "structured-ip-noretry", "structured-sqp",
            "fast-sqp", "robust-sqp"} <= set(emitted)
    stop = EMITTED_STOP_OPTIONS["ipopt"]
    for name in emitted:
        c = compile(_small_ocp(), name)
        assert c.as_emitted, name
        assert c._retry_options("ipopt", {}).items() >= stop.items(), name
    c = compile(_small_ocp(), "structured-ip")
    assert c.lowering == "expanded" and c.stages is not None  # unchanged: stage order
    assert [n for n, _ in c.retries] == ["fatrop", "ipopt"]
