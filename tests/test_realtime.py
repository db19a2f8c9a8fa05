"""The real-time mode (issue #14 §5): budgets on the NLP solvers, truncated solves reported as
such (never optimal, no retry after a budget stop), and the truncation policy of the PCBF
filter in closed loop on the pendulum."""

from __future__ import annotations

import pickle
import time

import numpy as np
import pytest

from balustrade.backends import Solution, Status, compile
from balustrade.backends.targets import REALTIME_ITERATIONS, Budget, target
from balustrade.control import PCBFSafetyFilter, simulate
from balustrade.control.base import TRUNCATED, Trace, outcome
from balustrade.errors import BalustradeError, SolverError

#: a state of the pendulum where (2.24) needs 4 SQP iterations from a cold start
HARD = np.array([0.3, 1.4])
STATES = [np.array([psi, omega]) for psi in (-0.3, 0.0, 0.3, 0.45)
          for omega in (-1.4, 0.0, 0.8, 1.4)]


@pytest.fixture(scope="module")
def rt(pend):
    """The pendulum's (2.24) and (2.23) on the real-time preset and on a 1-iteration SQP."""
    one = target("fast-sqp").with_budget(iterations=1)
    return {"slack": compile(pend.slack, "real-time"), "filter": compile(pend.filter, "real-time"),
            "slack1": compile(pend.slack, one), "filter1": compile(pend.filter, one)}


# -- targets ----------------------------------------------------------------------------
def test_realtime_preset_and_budgets_map_to_solver_options():
    t = target("real-time")
    assert t.nlp_solver == "sqpmethod" and t.retries == ()
    assert t.budget == Budget(iterations=REALTIME_ITERATIONS)
    assert t.options["max_iter"] == REALTIME_ITERATIONS
    ip = target("exact").with_budget(iterations=7, seconds=0.05)
    assert ip.options["ipopt.max_iter"] == 7 and ip.options["ipopt.max_wall_time"] == 0.05
    assert ip.retries == () and pickle.loads(pickle.dumps(ip)).budget == ip.budget
    # another solver keeps the budget in its own option names
    moved = target("real-time").with_solver("ipopt")
    assert moved.options["ipopt.max_iter"] == REALTIME_ITERATIONS
    assert "max_iter" not in moved.options and moved.budget == t.budget
    with pytest.raises(SolverError, match="no seconds budget"):
        ip.with_solver("sqpmethod")
    # NumPy scalars are numbers too (e.g. a cap read from an array of settings)
    assert target("exact").with_budget(np.int64(7), np.float32(0.5)).budget == Budget(7, 0.5)
    # other options, or the budget's own value, may still be added
    tuned = t.with_options({"max_iter": REALTIME_ITERATIONS, "print_time": False})
    assert tuned.budget == t.budget and tuned.options["print_time"] is False


@pytest.mark.parametrize("call, words", [
    (lambda: target("fast-sqp").with_budget(seconds=0.01), "no seconds budget"),
    (lambda: target("cvxpy").with_budget(iterations=3), "CasADi"),
    (lambda: target("exact").with_budget(iterations=0), "positive int"),
    (lambda: target("exact").with_budget(seconds=-1.0), "positive finite"),
    (lambda: target("exact").with_budget(), "give iterations"),
    (lambda: target("real-time").with_options(max_iter=100), "set by the budget"),
    (lambda: target("real-time", options={"max_iter": 100}), "set by the budget"),
])
def test_bad_budgets_are_refused(call, words):
    with pytest.raises(SolverError, match=words):
        call()


@pytest.mark.parametrize("backend", ["cvxpy", "direct", "auto"])
def test_a_budget_on_a_backend_that_ignores_it_is_refused(backend):
    from balustrade.backends.targets import Target

    with pytest.raises(SolverError, match="budgets are for the CasADi"):
        Target(backend, None, budget=Budget(iterations=3))


def test_a_truncated_solution_cannot_claim_optimal():
    with pytest.raises(BalustradeError, match="truncated"):
        Solution("optimal", 0.0, {}, {}, 0.0, 1, "casadi", "sqpmethod", truncated=True)
    # nor become optimal later, whichever attribute is set last
    sol = Solution("max_iterations", 0.0, {}, {}, 0.0, 1, "casadi", "sqpmethod",
                   truncated=True)
    for status in ("optimal", "optimal_inaccurate"):
        with pytest.raises(BalustradeError, match="truncated"):
            sol.status = status
    assert sol.status == "max_iterations"
    ok = Solution("optimal", 0.0, {}, {}, 0.0, 1, "casadi", "sqpmethod")
    with pytest.raises(BalustradeError, match="truncated"):
        ok.truncated = True
    assert not ok.truncated
    sol.truncated, sol.status = False, "optimal"  # no longer truncated: allowed


# -- backend reporting --------------------------------------------------------------------
@pytest.mark.parametrize("name, cap", [("slack", REALTIME_ITERATIONS), ("slack1", 1),
                                       ("filter", REALTIME_ITERATIONS), ("filter1", 1)])
def test_iterations_never_exceed_the_cap_and_stops_are_truncated(pend, rt, name, cap):
    seen = set()
    for x in STATES:
        params = {"x0": x} if name.startswith("slack") else {
            "x0": x, "u_p": np.array([2.0]), "xi": np.zeros((4, pend.N)), "xi_N": 0.0}
        sol = rt[name].solve(params)
        assert sol.iterations <= cap, sol.summary()
        seen.add(sol.status)
        if sol.status == Status.MAX_ITERATIONS:
            assert sol.truncated and not sol.success and not sol.usable
            assert np.isfinite(sol.primal_residual) and sol.primal_residual >= 0.0
            assert "truncated" in sol.summary() and "after retries" not in sol.message
        else:
            assert not sol.truncated
    if cap == 1 and name == "slack1":
        assert Status.MAX_ITERATIONS in seen  # the cap is reached on this grid


def test_truncated_solve_is_reported_with_its_residual(rt):
    sol = rt["slack1"].solve({"x0": HARD})
    assert sol.status == "max_iterations" and sol.status != "optimal"
    assert sol.truncated and sol.iterations == 1 and sol.solver == "sqpmethod"
    assert sol.feasible_within(np.inf) and sol.feasible_within() == (sol.primal_residual <= 1e-8)
    # the same cap without a budget is an ordinary iteration limit: retries, no truncation
    plain = compile(rt["slack1"].ocp, "fast-sqp", options={"max_iter": 1})
    other = plain.solve({"x0": HARD})
    assert not other.truncated and "after retries" in other.message


def test_no_retry_after_a_budget_stop(pend, monkeypatch):
    """A retry chain put back on a budgeted target still does not run after a budget stop
    (it would break the time bound); it does run after other failures."""
    tgt = target("fast-sqp").with_budget(iterations=1).with_retries([("ipopt", {})])
    prob = compile(pend.slack, tgt)
    called = []
    monkeypatch.setattr(type(prob), "_retry_solvers",
                        lambda self: called.append(1) or [])
    sol = prob.solve({"x0": HARD})
    assert sol.truncated and called == [], sol.summary()
    # IPOPT's wall-clock budget: stopped at once, truncated, no cold retry
    ip = compile(pend.slack, target("exact").with_budget(seconds=1e-9).with_retries(None))
    monkeypatch.setattr(type(ip), "_retry_solvers", lambda self: called.append(1) or [])
    sol = ip.solve({"x0": HARD})
    assert sol.status == "max_iterations" and sol.truncated and called == []
    assert "WallTime" in sol.message


# -- controllers ----------------------------------------------------------------------------
class _Truncating:
    """A compiled problem whose solves are cut as if by a budget, at a chosen residual."""

    def __init__(self, inner, residual: float):
        self.inner, self.ocp, self.residual = inner, inner.ocp, residual

    def solve(self, params=None, warm_start=None) -> Solution:
        sol = self.inner.solve(params)
        sol.status, sol.truncated, sol.primal_residual = "max_iterations", True, self.residual
        return sol


def test_feasible_truncated_filter_is_applied_and_flagged(pend):
    ctl = PCBFSafetyFilter(pend.compiled["slack", "casadi"],
                           _Truncating(pend.compiled["filter", "casadi"], 0.0), pend.U)
    u, info = ctl.step(np.array([0.0, 1.0]), np.array([2.0]))
    assert info.fallback is None and info.uncertified == {"filter": TRUNCATED}
    assert info.status == "slack_optimal_filter_truncated" and np.isfinite(info.values["h_PB"])
    assert u[0] == pytest.approx(info.solutions["filter"]["u"][0, 0])


def test_infeasible_truncated_filter_is_a_failed_filter(pend):
    ctl = PCBFSafetyFilter(pend.compiled["slack", "casadi"],
                           _Truncating(pend.compiled["filter", "casadi"], 1e-3), pend.U)
    u, info = ctl.step(np.array([0.0, 1.0]), np.array([2.0]))
    assert info.fallback == "slack_solution" and info.status == "filter_truncated"
    assert u[0] == pytest.approx(info.solutions["slack"]["u"][0, 0])


def test_truncated_slack_is_an_upper_bound_only(pend):
    x = np.array([0.45, 1.2])  # h_PB > 0 here
    ctl = PCBFSafetyFilter(_Truncating(pend.compiled["slack", "casadi"], 0.0),
                           pend.compiled["filter", "casadi"], pend.U)
    u, info = ctl.step(x, np.array([2.0]))
    assert np.isnan(info.values["h_PB"]) and info.values["h_PB_upper"] > 0
    assert info.fallback == "feasible_slack" and info.uncertified["slack"] == TRUNCATED
    assert info.status.startswith("slack_truncated")
    # stopped infeasible: a failed (2.24), nothing of it is used
    bad = PCBFSafetyFilter(_Truncating(pend.compiled["slack", "casadi"], 1.0),
                           pend.compiled["filter", "casadi"], pend.U)
    u, info = bad.step(x, np.array([5.0]))
    assert info.fallback == "projected_proposal" and info.status == "slack_truncated"
    assert "h_PB" not in info.values and u[0] == 3.0


def test_outcome_word():
    sol = Solution("max_iterations", 0.0, {}, {}, 0.0, 1, "casadi", "sqpmethod",
                   truncated=True)
    assert outcome(sol) == TRUNCATED
    sol.truncated = False
    assert outcome(sol) == "max_iterations"


def test_robust_filter_truncation_policy(unstable2d_tube):
    """Algorithm 5.2: a feasible truncated (5.16) is applied, flagged; a truncated (5.15)
    is a failed (5.15) whose cost is recorded only as an upper bound ``h_r_upper``."""
    from balustrade.control.robust import RobustPCBFSafetyFilter
    from balustrade.problems.robust import robust_pcbf_filter_problem

    t = unstable2d_tube
    system, s, error, cbf = t["system"], t["s"], t["error"], t["cbf"]
    filt = robust_pcbf_filter_problem(system, s.X, s.U, cbf, t["N"], s.deltas(), error)
    slack = compile(t["slack"], "exact")
    filt_c = compile(filt, "robust-sqp")
    x, u_p = np.array([0.3, 0.5]), np.array([2.0])

    def make(sl, fi):
        return RobustPCBFSafetyFilter(sl, fi, system, t["X_E"], s.U, error, cbf, cbf.policy,
                                      s.deltas(), s.alpha_f)

    ctl = make(slack, _Truncating(filt_c, 0.0))
    u, info = ctl.step(x, u_p)
    assert info.fallback is None and info.uncertified == {"filter": TRUNCATED}
    assert info.status == "filter_truncated" and np.isfinite(info.values["h_r"])
    ctl = make(slack, filt_c)
    ctl.step(x, u_p)
    assert ctl._last_filter is not None  # a converged (5.16) is the next warm start
    ctl.filter = _Truncating(filt_c, 1e-3)
    u, info = ctl.step(x, u_p)
    assert info.fallback == "slack_solution" and info.status == "filter_truncated"
    assert ctl._last_filter is None  # stopped infeasible: restart from (5.15), as in pcbf
    ctl = make(_Truncating(slack, 0.0), filt_c)
    u, info = ctl.step(x, u_p)
    assert "h_r" not in info.values and info.values["h_r_upper"] >= 0.0
    assert info.status == "slack_truncated" and info.fallback == "projected_proposal"


class _CPUTimed:
    """A controller wrapper recording the process (CPU) time of each step: under load the
    wall-clock worst case is the scheduler's, the CPU time is the solver's."""

    def __init__(self, inner):
        self.inner, self.times = inner, []

    def step(self, x, u_p):
        start = time.process_time()
        out = self.inner.step(x, u_p)
        self.times.append(time.process_time() - start)
        return out

    def reset(self):
        self.inner.reset()


def test_realtime_closed_loop_keeps_the_state_constraints(pend, tmp_path):
    """The pendulum PCBF on the real-time preset (at most 3 SQP iterations per solve): the
    seeded runs keep ψ <= 0.5, |ω| <= 1.5, |u| <= 3, record their truncations, and a
    truncated solve is only ever applied when feasible. Prints the worst-case step time
    (a report, no timed assertion)."""
    ctl = PCBFSafetyFilter.build(pend.system, pend.X, pend.U, pend.h_f, pend.N, pend.deltas,
                                 target="real-time")
    rng = np.random.default_rng(7)
    worst, cpu, truncated = [], [], 0
    for omega0 in (-1.5, 0.75, 1.5):
        timed = _CPUTimed(ctl)
        timed.reset()
        proposals = rng.uniform(-3.0, 3.0, size=150)
        trace = simulate(pend.system, timed, [0.0, omega0], 150,
                         proposal=lambda k, x, p=proposals: np.array([p[k] + 2.0]),
                         keep_infos=True)
        assert trace.stopped is None
        assert np.max(trace.states[:, 0]) <= 0.5 + 1e-6
        assert np.max(np.abs(trace.states[:, 1])) <= 1.5 + 1e-6
        assert np.all(np.abs(trace.inputs) <= 3.0 + 1e-9)
        for info in trace.infos:
            sols = info.solutions.values()
            assert all(s.iterations <= REALTIME_ITERATIONS for s in sols)
            if any(s.truncated for s in sols):
                assert TRUNCATED in info.status and info.status != "ok"
            f = info.solutions.get("filter")
            if f is not None and f.truncated and info.fallback is None:
                assert f.feasible_within() and info.uncertified["filter"] == TRUNCATED
        truncated += trace.n_truncated
        if trace.n_truncated:  # the record survives a saved run
            trace.save(tmp_path / f"run{omega0}")
            assert Trace.load(tmp_path / f"run{omega0}").n_truncated == trace.n_truncated
            fig = trace.plot()
            events = fig.get_axes()[-1]
            assert [t.get_text() for t in events.get_yticklabels()][-1] == TRUNCATED
            assert f"{trace.n_truncated} truncated" in fig._suptitle.get_text()
        worst.append(trace.step_times[1:])
        cpu.append(timed.times[1:])
    assert truncated >= 1  # the cap is reached and recorded on these runs
    wall, cpu = np.concatenate(worst) * 1e3, np.concatenate(cpu) * 1e3
    print(f"\nreal-time pendulum PCBF: {truncated} truncated steps of 450; step time (after "
          f"the first step, under load) wall median {np.median(wall):.3f} / p99 "
          f"{np.percentile(wall, 99):.2f} / worst {wall.max():.2f} ms, CPU median "
          f"{np.median(cpu):.3f} / worst {cpu.max():.2f} ms")


# -- the emitted C (issue #14 §5): truncation reported as Python reports it -----------------
def test_budget_switches_off_the_small_step_stop():
    """Under a budget sqpmethod stops only by converging or by the budget (the C tells a
    truncated solve by that), and the companion option follows the solver."""
    from balustrade.backends.targets import BUDGET_COMPANIONS

    t = target("real-time")
    assert t.options["min_step_size"] == BUDGET_COMPANIONS["sqpmethod"]["min_step_size"] < 0
    assert "min_step_size" not in t.with_solver("ipopt").options
    with pytest.raises(SolverError, match="set by the budget"):
        t.with_options(min_step_size=1e-10)


@pytest.fixture(scope="module")
def rt_c(pend, tmp_path_factory):
    """The pendulum PCBF on the real-time preset, in Python and emitted as C."""
    from balustrade.codegen import CPCBFSafetyFilter, build, emit_pcbf

    ctl = PCBFSafetyFilter.build(pend.system, pend.X, pend.U, pend.h_f, pend.N, pend.deltas,
                                 target="real-time")
    out = tmp_path_factory.mktemp("rt_pcbf")
    emitted = emit_pcbf(ctl, "rtpend", out)
    lib = build(out, emitted.name, werror=True)
    return {"py": ctl, "c": CPCBFSafetyFilter(lib), "out": out, "emitted": emitted}


def test_emitted_budget_and_truncated_status(rt_c):
    from balustrade.codegen import status as S

    assert S.code_of(S.SOLVE, "truncated") not in (S.code_of(S.SOLVE, "ok"),
                                                   S.code_of(S.SOLVE, "feasible"))
    config = (rt_c["out"] / "rtpend_config.h").read_text()
    assert f"#define rtpend_slack_BUDGET {REALTIME_ITERATIONS}" in config
    assert "#define BAL_TRUNCATED 6" in config
    assert "#define rtpend_slack_N_SOLVERS 1" in config  # no retry after a budget stop
    assert rt_c["emitted"].manifest["problems"]["slack"]["budget"] == REALTIME_ITERATIONS


def test_c_step_reports_truncation_exactly_as_python(pend, rt_c):
    """C = Python on real-time closed loops of the pendulum: the same truncated flags
    (status words, uncertified record, ``Trace.n_truncated``), fallbacks and inputs."""
    py, c = rt_c["py"], rt_c["c"]
    rng = np.random.default_rng(7)
    truncated = 0
    for omega0 in (-1.5, 0.75, 1.5):
        proposals = rng.uniform(-3.0, 3.0, size=60)
        runs = []
        for ctl in (py, c):
            ctl.reset()
            runs.append(simulate(pend.system, ctl, [0.0, omega0], 60, keep_infos=True,
                                 proposal=lambda k, x, p=proposals: np.array([p[k] + 2.0])))
        t1, t2 = runs
        assert [i.status for i in t1.infos] == [i.status for i in t2.infos]
        assert [i.uncertified for i in t1.infos] == [i.uncertified for i in t2.infos]
        assert t1.fallbacks == t2.fallbacks and t1.n_truncated == t2.n_truncated
        assert np.abs(t1.inputs - t2.inputs).max() <= 1e-6
        truncated += t2.n_truncated
    assert truncated >= 1  # the budget is reached and reported by the C


def test_emitted_robust_step_reports_truncation_as_python(unstable2d_tube, tmp_path):
    """Algorithm 5.2 with a 5-iteration SQP budget, Python and its emitted C (§5.6 system,
    N = 10): the same status words, uncertified record, ``h_r_upper``, fallbacks and inputs
    along closed loops in which (5.15) and (5.16) are truncated — a feasible truncated
    (5.16) applied, infeasible ones replaced by the (5.15) solution and restarted from it
    (3 iterations, the real-time preset, rarely get (5.15) feasible from a cold start)."""
    from balustrade.codegen import CRobustPCBFSafetyFilter, build, emit_robust
    from balustrade.control.robust import RobustPCBFSafetyFilter

    t = unstable2d_tube
    system, s = t["system"], t["s"]
    budget = target("robust-sqp").with_budget(iterations=5)
    from balustrade.dsl.policies import AffinePolicy

    # π_f as an explicit affine law: a numpy-only policy cannot be emitted (session 13)
    py = RobustPCBFSafetyFilter.build(system, s.X, s.U, t["cbf"], AffinePolicy(t["cbf"].K),
                                      t["N"], s.deltas(), t["error"], s.alpha_f, slack_norm=1,
                                      target=budget, slack_target=budget)
    emitted = emit_robust(py, "rtrob", tmp_path)
    c = CRobustPCBFSafetyFilter(build(tmp_path, emitted.name, werror=True))
    rng = np.random.default_rng(3)
    truncated, applied = 0, 0
    for x0 in ([-0.2, 0.0], [0.5, 2.0]):
        proposals = rng.uniform(-4.0, 4.0, size=30)
        runs = []
        for ctl in (py, c):
            ctl.reset()
            runs.append(simulate(system, ctl, x0, 30, keep_infos=True,
                                 proposal=lambda k, x, p=proposals: np.array([p[k]])))
        t1, t2 = runs
        assert [i.status for i in t1.infos] == [i.status for i in t2.infos]
        assert [i.uncertified for i in t1.infos] == [i.uncertified for i in t2.infos]
        assert t1.fallbacks == t2.fallbacks
        for a, b in zip(t1.infos, t2.infos):
            assert ("h_r_upper" in a.values) == ("h_r_upper" in b.values)
            if "h_r_upper" in a.values:
                assert a.values["h_r_upper"] == pytest.approx(b.values["h_r_upper"], abs=1e-6)
        assert np.abs(t1.inputs - t2.inputs).max() <= 1e-6
        truncated += t2.n_truncated
        applied += sum(i.uncertified.get("filter") == TRUNCATED for i in t2.infos)
    assert truncated >= 1 and applied >= 1


def test_multiobjective_records_truncation_with_the_word(unstable2d_tube):
    """Algorithm 6.4 treats a truncated (6.15) as a failed one (the candidate) and records
    it as ``problem_truncated`` (it recorded the bare ``max_iterations``, which
    ``Trace.n_truncated`` did not count); the C runtime reads ``BAL_TRUNCATED`` the same."""
    from balustrade.codegen import status as S
    from balustrade.codegen.runtime_robust import multiobjective_info
    from balustrade.control.multiobjective import MultiobjectivePCBFController

    t = unstable2d_tube
    system, s = t["system"], t["s"]
    ctl = MultiobjectivePCBFController.build(system, s.X, s.U, t["cbf"], t["cbf"].policy,
                                             t["N"], s.deltas(), t["error"], s.alpha_f,
                                             target="exact", slack_target="exact")
    ctl.problem = _Truncating(ctl.problem, 0.0)
    x = np.array([0.3, 0.5])
    ctl.step(x, np.array([0.5]))
    _, info = ctl.step(x, np.array([0.5]))
    assert info.status == "problem_truncated" and info.fallback == "warm_start"
    trunc = S.code_of(S.SOLVE, "truncated")
    c_info = multiobjective_info(S.code_of(S.MULTIOBJ, "warm_start"), S.code_of(S.SOLVE, "ok"),
                                 trunc, np.full(3, np.nan))
    assert c_info.status == "problem_truncated" and c_info.fallback == "warm_start"
