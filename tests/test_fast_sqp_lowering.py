"""``fast-sqp`` solves, in Python, the NLP its emitted C is generated from (issue #14, "C for
every closed loop, the same answers as Python").

The emitters generate the C of every ``sqpmethod`` target from the compact lowering
(``codegen.emit.EMIT_LOWERING``); until session 12 the ``fast-sqp`` presets solved the
expanded one in Python — the same maths with other rounding, the gap session 11 closed for
``robust-sqp`` (tests/test_lane_c_chain.py). Here the C of the emitted controllers on these
presets is compared with Python on the *preset as shipped* (retries mirrored to the C's
chain, :func:`~balustrade.codegen.runtime.mirror_c_retries`): statuses equal, inputs within
1e-6, on random states and along closed loops — pendulum PCBF pair (``emit_pcbf``), one
problem (``emit_problem``), Algorithm 7.5 (``emit_approximate``); the cart-pole pair
(nonlinear RK4 dynamics, where the two lowerings round differently) is the slow test.

``python -m tests.test_fast_sqp_lowering [n_states] [cartpole_states]`` prints the largest
differences for both Python lowerings against the same C, ``... timing n n_cartpole`` the
Python step times of both lowerings, interleaved (the numbers of docs/engines.md).
"""

from __future__ import annotations

import re
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

from balustrade.backends import PRESETS
from balustrade.backends.casadi_backend import AS_EMITTED
from balustrade.backends.targets import Target, target
from balustrade.codegen import (
    CApproximatePCBFFilter,
    CPCBFSafetyFilter,
    CProblem,
    build,
    emit_approximate,
    emit_pcbf,
    emit_problem,
)
from balustrade.codegen.emit import EMIT_LOWERING
from balustrade.codegen.runtime import mirror_c_retries
from balustrade.control.base import simulate
from balustrade.errors import SolverError

#: the presets whose C the emitters generate from the compact lowering (sqpmethod, not in
#: stage order): each must solve that lowering in Python too
EMITTED_SQP_PRESETS = ("fast-sqp", "fast-sqp-noretry", "robust-sqp", "convex-qp", "real-time")


def _lowered(name: str, lowering: str | None) -> Target:
    """Preset ``name`` as shipped (``lowering`` None) or on the given lowering."""
    t = PRESETS[name]
    return t if lowering is None else t.with_options(lowering=lowering)


def pendulum_pair(lowering: str | None = None):
    """The pendulum PCBF filter of ``examples.codegen`` on ``fast-sqp`` (``lowering``: as
    shipped or forced), retries mirrored to the C's chain."""
    from balustrade.control.pcbf import PCBFSafetyFilter
    from balustrade.examples.pendulum import pendulum_terminal_cbf
    from balustrade.models.pendulum import pendulum, pendulum_setup

    s = pendulum_setup()
    py = PCBFSafetyFilter.build(pendulum(), s.X, s.U, pendulum_terminal_cbf(), s.N,
                                s.deltas, s.alpha_f, slack_norm=1,
                                target=_lowered("fast-sqp", lowering))
    py.slack, py.filter = mirror_c_retries(py.slack), mirror_c_retries(py.filter)
    return py


def pendulum_approximate(lowering: str | None = None):
    """Algorithm 7.5 of ``examples.codegen`` on ``fast-sqp``, retries mirrored."""
    from balustrade.control.approximate import ApproximatePCBFFilter
    from balustrade.examples.pendulum import pendulum_terminal_cbf
    from balustrade.models.pendulum import pendulum, pendulum_setup

    py = ApproximatePCBFFilter(pendulum(), pendulum_setup().U, pendulum_terminal_cbf(),
                               target=_lowered("fast-sqp", lowering))
    py.decrease.compiled = mirror_c_retries(py.decrease.compiled)
    py.filter = mirror_c_retries(py.filter)
    return py


def cartpole_pair(lowering: str | None = None, design=None):
    """The cart-pole PCBF pair (RK4, N = 20) on ``fast-sqp``, retries mirrored."""
    from balustrade.control import PCBFSafetyFilter
    from balustrade.examples.cartpole import cartpole_design, cartpole_problems

    d = cartpole_design() if design is None else design
    slack, filt = cartpole_problems(_lowered("fast-sqp", lowering), design=d)
    return PCBFSafetyFilter(mirror_c_retries(slack), mirror_c_retries(filt), d.U), d


def _pendulum_states(seed: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.uniform([-0.7, -2.0], [0.7, 2.0], size=(n, 2)), rng.uniform(-4, 4, size=(n, 1))


#: the Python statuses of a problem that did not converge, all ``not_converged`` in the C
#: (its solvers return no status: BAL_NOT_CONVERGED, codegen.status.SOLVE)
_NOT_CONVERGED = re.compile(r"(max_iterations|failed|infeasible)$")


def _norm(status: object) -> str:
    return _NOT_CONVERGED.sub("not_converged", str(status))


def same_outcome(i1, i2) -> bool:
    """The Python step info ``i1`` and the C's ``i2`` say the same (status and fallback; the
    statuses of unconverged solves by the C's one name)."""
    a, b = _norm(i1.status), _norm(i2.status)
    return (a, i1.fallback) == (b, i2.fallback)


def _gap(a, b) -> float:
    """Largest |a − b|; ``inf`` when a value is not finite on either side (``max`` would
    otherwise drop a NaN and let it pass a tolerance)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        return float("inf")
    return float(np.abs(a - b).max()) if a.size else 0.0


def compare_steps(py, c, states, proposals, log: list | None = None) -> tuple[float, int]:
    """(largest |u_py − u_c|, number of steps whose status or fallback differ), each step
    from a cold start; ``log`` collects ``(x, python info, C info)`` of the differing."""
    du, mismatches = 0.0, 0
    for x, u_p in zip(states, proposals):
        py.reset()
        c.reset()
        u1, i1 = py.step(x, u_p)
        u2, i2 = c.step(x, u_p)
        du = max(du, _gap(u1, u2))
        if not same_outcome(i1, i2):
            mismatches += 1
            if log is not None:
                log.append((x, i1, i2))
    return du, mismatches


def compare_loops(py, c, system, starts, steps: int) -> tuple[float, int]:
    """(largest input difference, steps with different statuses) along closed loops from
    ``starts`` with a constant and a sinusoidal proposal."""
    du, mismatches = 0.0, 0
    for x0 in starts:
        for proposal in (2.0, lambda k, x: 3.5 * np.sin(0.4 * k)):
            py.reset()
            c.reset()
            t1 = simulate(system, py, x0, steps, proposal=proposal)
            t2 = simulate(system, c, x0, steps, proposal=proposal)
            n = min(len(t1.inputs), len(t2.inputs))
            du = max(du, _gap(t1.inputs[:n], t2.inputs[:n]))
            mismatches += sum(_norm(a) != _norm(b) for a, b in zip(t1.statuses, t2.statuses))
            mismatches += abs(len(t1.inputs) - len(t2.inputs))
    return du, mismatches


def compare_problem(slack, prob: CProblem, states) -> tuple[float, int]:
    """(largest |w_py − w_c| where both converged, status disagreements) of one problem."""
    dw, mismatches = 0.0, 0
    for x in states:
        sol = slack.solve({"x0": x})
        status, _, _, w = prob.solve({"x0": x}, warm=False)
        py_status = str(getattr(sol.status, "value", sol.status))
        mismatches += (status == "ok") != sol.success
        mismatches += (status == "feasible") != (py_status == "feasible")
        if status in ("ok", "feasible") and (sol.success or py_status == "feasible"):
            dw = max(dw, _gap(w[: slack.layout.user_size], sol.w))
    return dw, mismatches


# -- tests ----------------------------------------------------------------------------------
def test_every_emitted_sqp_preset_solves_the_lowering_its_c_is_generated_from():
    for name in EMITTED_SQP_PRESETS:
        assert PRESETS[name].options.get("lowering") == AS_EMITTED, name


def test_stage_ordered_variants_of_the_emitted_presets_still_compile():
    """The presets carry ``as-emitted``, not ``compact``: a user's ``fast-sqp`` with
    ``qpsol="hpipm"`` or with fatrop compiled before session 12 and must still compile (on
    the expanded NLP in stage order, what their C is generated from); an explicit
    ``compact`` with a stage-ordered solver is refused, naming the lowering. (Fails when the
    presets carry ``"compact"``: SolverError about a lowering the user never set.)"""
    from balustrade.control.pcbf import PCBFSafetyFilter
    from balustrade.examples.pendulum import pendulum_terminal_cbf
    from balustrade.models.pendulum import pendulum, pendulum_setup

    s = pendulum_setup()

    def slack_of(t: Target):
        return PCBFSafetyFilter.build(pendulum(), s.X, s.U, pendulum_terminal_cbf(), s.N,
                                      s.deltas, s.alpha_f, slack_norm=1, target=t).slack

    for t in (PRESETS["fast-sqp"].with_options(qpsol="hpipm"),
              target("fast-sqp", options={"qpsol": "hpipm"}),
              PRESETS["fast-sqp"].with_solver("fatrop"),
              PRESETS["robust-sqp"].with_options(qpsol="hpipm")):
        c = slack_of(t)
        assert c.lowering == "expanded" and c.stages is not None, t.name
    assert slack_of(PRESETS["fast-sqp"]).lowering == EMIT_LOWERING
    with pytest.raises(SolverError, match="compact"):
        slack_of(PRESETS["fast-sqp"].with_options(qpsol="hpipm", lowering="compact"))


@pytest.fixture(scope="module")
def pendulum_c(tmp_path_factory: pytest.TempPathFactory) -> dict:
    from balustrade.models.pendulum import pendulum

    out = tmp_path_factory.mktemp("fastsqp_pend")
    py = pendulum_pair()
    emitted = emit_pcbf(py, "fsp", out, dynamics=pendulum().function)
    return {"py": py, "lib": build(out, emitted.name, werror=True), "out": out}


def test_python_pendulum_pair_solves_the_compact_lowering(pendulum_c: dict) -> None:
    py = pendulum_c["py"]
    assert py.slack.lowering == EMIT_LOWERING and py.filter.lowering == EMIT_LOWERING


def test_pendulum_pcbf_c_equals_python_on_100_states_and_a_loop(pendulum_c: dict) -> None:
    from balustrade.models.pendulum import pendulum

    py, c = pendulum_c["py"], CPCBFSafetyFilter(pendulum_c["lib"])
    X, UP = _pendulum_states(11, 100)
    du, bad = compare_steps(py, c, X, UP)
    assert bad == 0 and du <= 1e-6, (du, bad)
    du, bad = compare_loops(py, c, pendulum(), [np.array([0.45, -1.2])], 30)
    assert bad == 0 and du <= 1e-6, (du, bad)


@pytest.mark.slow
def test_pendulum_c_equals_python_on_1000_states(pendulum_c: dict, tmp_path) -> None:
    """The PCBF step, its slack problem (2.24) alone and Algorithm 7.5, 1000 states each,
    and closed loops."""
    from balustrade.models.pendulum import pendulum

    py, c = pendulum_c["py"], CPCBFSafetyFilter(pendulum_c["lib"])
    X, UP = _pendulum_states(12, 1000)
    du, bad = compare_steps(py, c, X, UP)
    assert bad == 0 and du <= 1e-6, (du, bad)
    rng = np.random.default_rng(13)
    starts = np.vstack([[0.3, 0.5], rng.uniform([-0.5, -1.5], [0.5, 1.5], size=(4, 2))])
    du, bad = compare_loops(py, c, pendulum(), starts, 40)
    assert bad == 0 and du <= 1e-6, (du, bad)
    emitted = emit_problem(py.slack, "fsps", tmp_path / "p")
    prob = CProblem(build(tmp_path / "p", emitted.name, werror=True))
    dw, bad = compare_problem(py.slack, prob, X)
    assert bad == 0 and dw <= 1e-6, (dw, bad)
    apx = pendulum_approximate()
    emitted = emit_approximate(apx, "fspa", tmp_path / "a", dynamics=pendulum().function)
    capx = CApproximatePCBFFilter(build(tmp_path / "a", emitted.name, werror=True))
    du, bad = compare_steps(apx, capx, X, UP)
    assert bad == 0 and du <= 1e-6, (du, bad)


@pytest.mark.slow
def test_cartpole_c_equals_python_on_states_and_a_loop(tmp_path) -> None:
    """The nonlinear case: where the expanded and compact NLPs round differently."""
    from balustrade.examples.cartpole import X0, destabilizing_proposal

    py, d = cartpole_pair()
    emitted = emit_pcbf(py, "fspc", tmp_path)
    c = CPCBFSafetyFilter(build(tmp_path, emitted.name, werror=True))
    states = d.X.sample(1000, np.random.default_rng(0)) * 0.5
    du, bad = compare_steps(py, c, states, [destabilizing_proposal(x, 0) for x in states])
    assert bad == 0 and du <= 1e-6, (du, bad)
    py.reset()
    c.reset()
    t1 = simulate(d.system, py, X0, 100, proposal=lambda k, x: destabilizing_proposal(x, k))
    t2 = simulate(d.system, c, X0, 100, proposal=lambda k, x: destabilizing_proposal(x, k))
    assert [_norm(a) for a in t1.statuses] == [_norm(b) for b in t2.statuses]
    assert np.abs(t1.inputs - t2.inputs).max() <= 1e-6


# -- measurement (docs/engines.md) -------------------------------------------------------
def _measure(n: int, n_cartpole: int) -> None:  # pragma: no cover - a report, not a test
    from balustrade.models.pendulum import pendulum

    out = Path(tempfile.mkdtemp(prefix="fastsqp_"))
    if n <= 0:
        _measure_cartpole(out, n_cartpole)
        return
    pys = {lw: pendulum_pair(lw) for lw in ("expanded", "compact")}
    emitted = emit_pcbf(pys["compact"], "fsp", out / "pcbf", dynamics=pendulum().function)
    c = CPCBFSafetyFilter(build(out / "pcbf", emitted.name, werror=True))
    X, UP = _pendulum_states(12, n)
    rng = np.random.default_rng(13)
    starts = np.vstack([[0.3, 0.5], rng.uniform([-0.5, -1.5], [0.5, 1.5], size=(4, 2))])
    for lw, py in pys.items():
        print(f"pendulum PCBF {lw}: states {compare_steps(py, c, X, UP)}, "
              f"loops {compare_loops(py, c, pendulum(), starts, 40)}", flush=True)
    emitted = emit_problem(pys["compact"].slack, "fsps", out / "prob")
    prob = CProblem(build(out / "prob", emitted.name, werror=True))
    for lw, py in pys.items():
        print(f"pendulum (2.24) emit_problem {lw}: {compare_problem(py.slack, prob, X)}",
              flush=True)
    apx = {lw: pendulum_approximate(lw) for lw in ("expanded", "compact")}
    emitted = emit_approximate(apx["compact"], "fspa", out / "apx",
                               dynamics=pendulum().function)
    capx = CApproximatePCBFFilter(build(out / "apx", emitted.name, werror=True))
    for lw, py in apx.items():
        print(f"pendulum Alg 7.5 {lw}: states {compare_steps(py, capx, X, UP)}, "
              f"loops {compare_loops(py, capx, pendulum(), starts, 40)}", flush=True)
    if n_cartpole > 0:
        _measure_cartpole(out, n_cartpole)


def obstacle_approximate(lowering: str | None = None):
    """The obstacle reproduction's Algorithm 7.5 (committed network, ``network=``) on its
    filter target (``fast-sqp``), retries mirrored."""
    from balustrade.control.approximate import ApproximatePCBFFilter
    from balustrade.learn.export import to_casadi
    from balustrade.learn.train import MLPModel
    from balustrade.models.obstacle_car import obstacle_car, obstacle_setup
    from balustrade.reproduce import obstacles as R

    model = MLPModel.load(R.NET)
    py = ApproximatePCBFFilter(obstacle_car(), obstacle_setup().U, to_casadi(model),
                               rho=R.RHO, target=_lowered(R.FILTER_TARGET, lowering),
                               network=model)
    py.decrease.compiled = mirror_c_retries(py.decrease.compiled)
    py.filter = mirror_c_retries(py.filter)
    return py


def _measure_obstacles(out: Path, n: int) -> None:  # pragma: no cover - a report
    from balustrade.models.obstacle_car import obstacle_setup

    pys = {lw: obstacle_approximate(lw) for lw in ("expanded", "compact")}
    emitted = emit_approximate(pys["compact"], "fsob", out / "obs")
    c = CApproximatePCBFFilter(build(emitted.out_dir, werror=True))
    rng = np.random.default_rng(0)
    X = rng.uniform([-2, -1.5, -np.pi, 0, -0.75], [2, 1.5, np.pi, 4, 0.75], (n, 5))
    U = obstacle_setup().U
    P = rng.uniform(U.lb, U.ub, (n, 2))
    for lw, py in pys.items():
        log: list = []
        print(f"obstacle car Alg 7.5 {lw}: states {compare_steps(py, c, X, P, log)}",
              flush=True)
        for x, i1, i2 in log[:5]:
            print(f"  x {np.round(x, 4)}: python {i1.status}/{i1.fallback}, C {i2.status}/"
                  f"{i2.fallback}", flush=True)
    from balustrade.reproduce import obstacles as R

    runc = R.closed_loops(c, R.NaiveMPC(), starts=R.STARTS, steps=40)
    for lw, py in pys.items():
        runp = R.closed_loops(py, R.NaiveMPC(), starts=R.STARTS, steps=40)
        du = max(float(np.abs(a["inputs"] - b["inputs"]).max()) for a, b in zip(runp, runc))
        bad = sum(_norm(s1) != _norm(s2) for a, b in zip(runp, runc)
                  for s1, s2 in zip(a["statuses"], b["statuses"]))
        print(f"obstacle car loops {lw}: {len(R.STARTS)} starts x 40 steps (naive MPC), "
              f"max du {du:.3g}, status mismatches {bad}", flush=True)


def _measure_cartpole(out: Path, n_cartpole: int) -> None:  # pragma: no cover - a report
    from balustrade.examples.cartpole import X0, cartpole_design, destabilizing_proposal

    d = cartpole_design()
    cps = {lw: cartpole_pair(lw, d)[0] for lw in ("expanded", "compact")}
    emitted = emit_pcbf(cps["compact"], "fspc", out / "cp")
    c = CPCBFSafetyFilter(build(out / "cp", emitted.name, werror=True))
    states = d.X.sample(n_cartpole, np.random.default_rng(0)) * 0.5
    props = [destabilizing_proposal(x, 0) for x in states]
    def proposal(k, x):
        return destabilizing_proposal(x, k)

    for lw, py in cps.items():
        log: list = []
        print(f"cart-pole PCBF {lw}: states {compare_steps(py, c, states, props, log)}",
              flush=True)
        for x, i1, i2 in log[:8]:
            print(f"  x {np.round(x, 4)}: python {i1.status}/{i1.fallback} "
                  f"{ {k: v.status for k, v in i1.solutions.items()} }, C {i2.status}/"
                  f"{i2.fallback}", flush=True)
        py.reset()
        c.reset()
        t1 = simulate(d.system, py, X0, 100, proposal=proposal)
        t2 = simulate(d.system, c, X0, 100, proposal=proposal)
        n_ = min(len(t1.inputs), len(t2.inputs))
        bad = sum(_norm(a) != _norm(b) for a, b in zip(t1.statuses, t2.statuses))
        print(f"cart-pole loop {lw}: du {np.abs(t1.inputs[:n_] - t2.inputs[:n_]).max():.3g}, "
              f"status mismatches {bad}", flush=True)


def _timing(n: int, n_cartpole: int) -> None:  # pragma: no cover - a report, not a test
    """Python step times, expanded vs compact, interleaved state by state (cold steps after
    a reset), medians and the median of the per-state ratios."""
    import time

    from balustrade.examples.cartpole import cartpole_design, destabilizing_proposal

    def run(name, pair, states, props):
        t = {lw: [] for lw in pair}
        for k, (x, u_p) in enumerate(zip(states, props)):
            order = list(pair) if k % 2 == 0 else list(pair)[::-1]
            for lw in order:
                pair[lw].reset()
                t0 = time.perf_counter()
                pair[lw].step(x, u_p)
                t[lw].append(time.perf_counter() - t0)
        e, c = np.array(t["expanded"]), np.array(t["compact"])
        print(f"{name}: median expanded {1e3 * np.median(e):.3f} ms, compact "
              f"{1e3 * np.median(c):.3f} ms, median ratio compact/expanded "
              f"{np.median(c / e):.3f}, worst {1e3 * e.max():.1f} / {1e3 * c.max():.1f} ms",
              flush=True)

    X, UP = _pendulum_states(21, n)
    run("pendulum PCBF step", {lw: pendulum_pair(lw) for lw in ("expanded", "compact")}, X, UP)
    run("pendulum Alg 7.5 step", {lw: pendulum_approximate(lw)
                                  for lw in ("expanded", "compact")}, X, UP)
    if n_cartpole > 0:
        d = cartpole_design()
        states = d.X.sample(n_cartpole, np.random.default_rng(5)) * 0.5
        run("cart-pole PCBF step", {lw: cartpole_pair(lw, d)[0]
                                    for lw in ("expanded", "compact")},
            states, [destabilizing_proposal(x, 0) for x in states])


if __name__ == "__main__":  # pragma: no cover
    if sys.argv[1:2] == ["timing"]:
        _timing(int(sys.argv[2]), int(sys.argv[3]))
    elif sys.argv[1:2] == ["obstacles"]:
        _measure_obstacles(Path(tempfile.mkdtemp(prefix="fastsqp_")), int(sys.argv[2]))
    else:
        _measure(int(sys.argv[1]) if len(sys.argv) > 1 else 1000,
                 int(sys.argv[2]) if len(sys.argv) > 2 else 0)
