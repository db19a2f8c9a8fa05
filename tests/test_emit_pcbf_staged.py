"""The PCBF step emitted for problems compiled in stage order (the ``structured-ip``
target, fatrop; issue #14): one C call per step, C = Python.

The solver's vector is in stage order (``[x_0, u_0, ξ_0, …]``), the layout's offsets are
not: the step reads layout element ``i`` as ``x[take[i]]`` projected onto the layout's
bounds, writes warm starts by the same map and takes ``h_PB`` from the declared cost at
that point (bal/pcbf.c). Reading the staged vector at the layout's offsets (the bug these
tests catch) gives other inputs and slacks at once.

Fast: the pendulum pair (N = 10) built through :func:`~balustrade.codegen.accelerate`
(links libfatrop/libblasfeo/libipopt of the casadi wheel), closed loops and 100 states.
Slow: 1000 states, a closed loop replayed under valgrind, the cart-pole closed loop."""

from __future__ import annotations

import shutil
from collections import Counter

import numpy as np
import pytest

from balustrade.backends import compile
from balustrade.codegen.build import run_under_valgrind
from balustrade.control import PCBFSafetyFilter, simulate
from balustrade.control.base import step_succeeded
from balustrade.errors import CodegenError
from balustrade.examples.pendulum import pendulum_terminal_cbf
from balustrade.models.pendulum import pendulum, pendulum_setup
from balustrade.problems.pcbf import pcbf_filter_problem, pcbf_slack_problem

TARGET = "structured-ip"
STARTS = ([0.5, -0.3], [-0.8, 0.6])
STEPS = 30


def _filter(target: str = TARGET, slack_norm: float = 1):
    system, s = pendulum(), pendulum_setup()
    args = (system, s.X, s.U, pendulum_terminal_cbf(), s.N, s.deltas)
    slack = compile(pcbf_slack_problem(*args, alpha_f=s.alpha_f, slack_norm=slack_norm),
                    target)
    return system, s, PCBFSafetyFilter(slack, compile(pcbf_filter_problem(*args), target),
                                       s.U)


@pytest.fixture(scope="module")
def staged(tmp_path_factory):
    from balustrade.codegen import accelerate

    system, s, py = _filter()
    c = accelerate(py, build_dir=tmp_path_factory.mktemp("staged_pcbf"), name="stpcbf",
                   werror=True)
    return {"system": system, "setup": s, "py": py, "c": c, "dir": c.accelerated["dir"]}


def _loops(system, ctl):
    rng = np.random.default_rng(3)
    runs = []
    for x0 in STARTS:
        proposals = rng.uniform(-4.0, 4.0, size=STEPS)
        ctl.reset()
        runs.append(simulate(system, ctl, x0, STEPS, keep_infos=True,
                             proposal=lambda k, x, p=proposals: np.array([p[k]])))
    return runs


def _same_step(a, b) -> None:
    assert (a.status, a.fallback, a.uncertified) == (b.status, b.fallback, b.uncertified)
    for key in ("h_PB", "h_PB_upper"):
        if key in a.values or key in b.values:
            np.testing.assert_allclose(b.values[key], a.values[key], atol=1e-6,
                                       equal_nan=True)


def test_the_module_links_fatrop_and_maps_the_stage_order(staged):
    m = staged["c"]._lib.manifest
    assert {"fatrop", "blasfeo"} <= set(m["libraries"])
    assert any("-lfatrop" == f for f in m["link_flags"])
    for key in ("slack", "filter"):
        take = np.asarray(m["problems"][key]["take"])
        assert sorted(take) == list(range(m["problems"][key]["nw"]))
        assert np.any(take != np.arange(take.size))  # a real permutation: the map matters
        assert m["problems"][key]["solver"] == "fatrop"
    config = (staged["dir"] / "stpcbf_config.h").read_text()
    assert "#define stpcbf_slack_STAGED 1" in config
    assert "stpcbf_slack_obj" in (staged["dir"] / "stpcbf_casadi.c").read_text()


def test_closed_loops_c_equals_python(staged):
    """Two closed loops: the same statuses, fallbacks, h_PB and inputs (within 1e-6;
    measured equal to the last bit: the same solver from the same warm starts)."""
    system = staged["system"]
    for t_py, t_c in zip(_loops(system, staged["py"]), _loops(system, staged["c"])):
        for a, b in zip(t_py.infos, t_c.infos):
            _same_step(a, b)
        assert np.abs(t_py.inputs - t_c.inputs).max() <= 1e-6
        assert np.abs(t_py.states - t_c.states).max() <= 1e-6


def _states_agree(staged, n: int, seed: int) -> tuple[Counter, int]:
    """``n`` states of X, each from a reset filter: C and Python take the same decisions
    (status, fallback, uncertified solves, ``h_PB``) and inputs at every one. Returns the
    count of each status and of the states with ``h_PB > 0`` (outside the safe set S_PB)."""
    py, c, s = staged["py"], staged["c"], staged["setup"]
    rng = np.random.default_rng(seed)
    statuses: Counter = Counter()
    outside = 0
    for x in s.X.sample(n, rng):
        u_p = rng.uniform(-3.0, 3.0, 1)
        py.reset()
        c.reset()
        (u_py, i_py), (u_c, i_c) = py.step(x, u_p), c.step(x, u_p)
        _same_step(i_py, i_c)
        np.testing.assert_allclose(u_c, u_py, atol=1e-6)
        statuses[i_py.status] += 1
        outside += i_py.values["h_PB"] > 1e-9
    return statuses, outside


def _every_state_ok(statuses: Counter, outside: int, n: int) -> None:
    """A reset filter has no stored plan, so no certificate: every step solves (2.24) and
    (2.23). (2.24) is feasible at every state (its slacks are free) and (2.23) then too
    (the optimizer of (2.24) is feasible for it, SPEC §2.7), and on the pendulum pair the
    solver converges on both: every state is a plain ``"ok"`` step (measured: 1000 of 1000
    at seed 2, 100 of 100 at seed 1; any other status is a solver failure this test should
    show). Both branches of the step are exercised: states inside S_PB (``h_PB = 0``) and
    outside (206 of 1000 at seed 2)."""
    assert statuses == Counter({"ok": n}), statuses
    assert 0.1 * n <= outside <= 0.9 * n, outside


def test_states_c_equals_python(staged):
    _every_state_ok(*_states_agree(staged, 100, 1), 100)


def test_keep_solutions_reads_the_layout(staged):
    """The runtime's solutions are the layout's variables (through ``take``), equal to
    Python's primal."""
    from balustrade.codegen import CPCBFSafetyFilter

    c = CPCBFSafetyFilter(staged["dir"] / "libstpcbf.so", keep_solutions=True)
    py = staged["py"]
    py.reset()
    x, u_p = np.array([0.3, 0.2]), np.array([1.0])
    _, i_py = py.step(x, u_p)
    _, i_c = c.step(x, u_p)
    for key in ("slack", "filter"):
        for name, val in i_py.solutions[key].primal.items():
            np.testing.assert_allclose(i_c.solutions[key][name], val, atol=1e-9)


def test_a_stage_order_that_lifts_variables_is_refused():
    """A row summing over all stages (like (6.15g)) becomes a running-sum state in stage
    order: the staged vector is no permutation of the layout, which the emitted step does
    not map (a CodegenError saying so, not a step reading wrong offsets); the emitters
    without the map refuse any staged problem."""
    import casadi as ca

    from balustrade.codegen.emit import _staged_take
    from balustrade.dsl import OCP, Box, LinearSystem, squared_norm, sum_norms

    ocp = OCP(LinearSystem(np.array([[1.0, 0.1], [0.0, 1.0]]), np.array([[0.0], [0.1]])), 4,
              name="lifted")
    ocp.initial_state(ocp.parameter("x0", 2))
    ocp.dynamics()
    ocp.input_constraint(Box([-1.0], [1.0]))
    xi = ocp.state_constraint(Box([-2.0, -2.0], [2.0, 2.0]), slack="variable")
    ocp.decrease(ca.sum1(ca.sum2(xi)), 3.0)
    ocp.minimize(sum_norms(xi, 1) + squared_norm(ocp.u))
    c = compile(ocp, TARGET)
    assert c.stages is not None
    with pytest.raises(CodegenError, match="lifts variables"):
        _staged_take(c, "lifted", staged_ok=True)
    with pytest.raises(CodegenError, match="only inside the PCBF step"):
        _staged_take(c, "lifted", staged_ok=False)
    _, _, py = _filter()
    assert _staged_take(py.slack, "slack", staged_ok=True) is not None


def test_the_noretry_target_emits_fatrop_alone(tmp_path):
    """``structured-ip-noretry``: the C runs fatrop only (no IPOPT to link), as Python."""
    from balustrade.codegen import emit_pcbf

    _, _, py = _filter("structured-ip-noretry")
    m = emit_pcbf(py, "noretry", tmp_path, allow_external=True).manifest
    assert set(m["libraries"]) == {"fatrop", "blasfeo"}
    assert all(m["problems"][k]["retries"] == [] for k in ("slack", "filter"))
    assert "noretry_slack_nlp_retry" not in (tmp_path / "noretry_config.h").read_text()


def test_the_staged_c_is_generated_from_the_compact_lowering(tmp_path, monkeypatch):
    """By default the solvers' derivatives are the compact lowering's (one stage function,
    mapped); with ``EMIT_LOWERING = "expanded"`` each solver derives its own from the
    expanded NLP (larger C, no stage map)."""
    import balustrade.codegen.emit as E

    _, _, py = _filter()
    E.emit_pcbf(py, "cmp", tmp_path / "c", allow_external=True)
    compact = (tmp_path / "c" / "cmp_casadi.c").read_text()
    monkeypatch.setattr(E, "EMIT_LOWERING", "expanded")
    E.emit_pcbf(py, "exp", tmp_path / "e", allow_external=True)
    expanded = (tmp_path / "e" / "exp_casadi.c").read_text()
    assert "/* rest_jac:(" in compact and "/* rest_jac:(" not in expanded
    assert expanded.count("/* nlp_jac_g:(") == 4 and compact.count("/* nlp_jac_g:(") == 2


@pytest.mark.slow
def test_1000_states_c_equals_python(staged):
    _every_state_ok(*_states_agree(staged, 1000, 2), 1000)


DRIVER = r"""
/* Replays the states and proposals of a Python loop through the emitted step. */
#include <stdio.h>
#include "stpcbf.h"
#include "replay.h"

int main(void) {
  stpcbf_work* wk = stpcbf_alloc();
  casadi_real u[stpcbf_NU], h;
  int k, st;
  if (!wk) return 1;
  for (k = 0; k < REPLAY_K; ++k) {
    stpcbf_step(REPLAY_X[k], REPLAY_U + k, u, &h, &st, wk);
    printf("%d %.17g\n", st, u[0]);
  }
  stpcbf_free(wk);
  return 0;
}
"""


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("valgrind") is None, reason="needs valgrind")
def test_replayed_loop_is_memory_clean_under_valgrind(staged):
    """A Python closed loop replayed through the C step by a driver without Python, under
    valgrind: no memory error, no leak, the same inputs."""
    from balustrade.codegen import build_executable

    py, out = staged["py"], staged["dir"]
    trace = _loops(staged["system"], py)[0]
    x = np.asarray(trace.states)[:STEPS]
    rows = ",\n".join("{" + ", ".join(f"{v:.17g}" for v in r) + "}" for r in x)
    props = [float(i) for i in np.random.default_rng(3).uniform(-4.0, 4.0, size=STEPS)]
    (out / "replay.h").write_text(
        f"#define REPLAY_K {STEPS}\nstatic const casadi_real REPLAY_X[{STEPS}][2] = "
        f"{{{rows}}};\nstatic const casadi_real REPLAY_U[{STEPS}] = "
        f"{{{', '.join(f'{v:.17g}' for v in props)}}};\n")
    (out / "driver.c").write_text(DRIVER)
    flags = tuple(staged["c"]._lib.manifest["link_flags"])
    exe = build_executable(out, main="driver.c", werror=True, extra_flags=flags)
    proc = run_under_valgrind(str(exe), timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    u_c = np.array([float(line.split()[1]) for line in proc.stdout.splitlines()])
    assert np.abs(u_c - np.asarray(trace.inputs).reshape(-1)).max() <= 1e-6


@pytest.fixture(scope="module")
def cartpole_c(tmp_path_factory):
    from balustrade.codegen import accelerate
    from balustrade.examples.cartpole import cartpole_design, cartpole_problems

    d = cartpole_design()
    py = PCBFSafetyFilter(*cartpole_problems(TARGET, design=d), d.U)
    c = accelerate(py, build_dir=tmp_path_factory.mktemp("cartpole_st"), name="cpst",
                   werror=True)
    return d, py, c


@pytest.mark.slow
def test_cartpole_closed_loop_c_equals_python(cartpole_c):
    """The cart-pole pair (RK4, N = 20) on fatrop: 100 steps of examples/cartpole.py, the
    C step at every state of the Python loop: the same statuses and inputs, no failure
    (:func:`~balustrade.control.base.step_succeeded`: ``"ok"`` or ``"certified"``),
    the state stays in X."""
    from balustrade.examples.cartpole import cartpole_scenario

    d, py, c = cartpole_c
    x, proposal = cartpole_scenario()
    py.reset()
    c.reset()
    for k in range(100):
        u_p = proposal(x, k)
        (u, i_py), (u_c, i_c) = py.step(x, u_p), c.step(x, u_p)
        _same_step(i_py, i_c)
        # certificate_first is the default: most steps are "certified" (no (2.24) solved)
        assert step_succeeded(i_py.status) and not i_py.fallback, (k, i_py)
        np.testing.assert_allclose(u_c, u, atol=1e-6)
        x = d.system.step(x, u)
        assert np.all(np.abs(x) <= d.X.h[:4] + 1e-9), (k, x)


@pytest.mark.slow
def test_cartpole_1000_states_c_equals_python(cartpole_c):
    """1000 states of the cart-pole's X (scaled by 0.5, as tests/test_cartpole.py), each
    from a reset filter with the scenario's proposal: the same decisions and inputs."""
    from balustrade.examples.cartpole import destabilizing_proposal

    d, py, c = cartpole_c
    rng = np.random.default_rng(0)
    ok = 0
    for x in d.X.sample(1000, rng) * 0.5:
        u_p = destabilizing_proposal(x, 0)
        py.reset()
        c.reset()
        (u_py, i_py), (u_c, i_c) = py.step(x, u_p), c.step(x, u_p)
        _same_step(i_py, i_c)
        np.testing.assert_allclose(u_c, u_py, atol=1e-6)
        ok += i_py.status == "ok"
    assert ok >= 500
