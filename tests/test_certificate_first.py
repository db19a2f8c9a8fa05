"""Certificate first (issue #14): the shifted last plan checked *before* the slack problem
(2.24); when it meets every row of (2.24) with zero slack, ``h_PB = 0`` is the global
optimum (the cost ``α_f ξ_N + Σ‖ξ_i‖`` is 0 only with every slack 0) and the solve is
skipped: (2.23) runs with ``ξ* = 0`` (:class:`~balustrade.control.pcbf.PCBFSafetyFilter`
``certificate_first``, on by default since session 11; bal/pcbf.c ``<name>_CERT_FIRST``).

Fast: the stable linear system of tests/test_emit_pcbf_cert.py on the ``real-time`` target
(the certificate fires at some steps and not at others: C = Python at both; and with the
option off, C = Python with no skip) and the pendulum pair on fatrop (``structured-ip``,
stage-ordered C); the negative control (a shifted plan that needs a positive slack never
skips (2.24)); the default and the option in the deployment spec, manifest and config
header. Slow: the cart-pole closed loop C = Python,
and a replayed loop under valgrind."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import scipy.linalg as sla

from balustrade.backends import compile
from balustrade.codegen.build import run_under_valgrind
from balustrade.control import PCBFSafetyFilter, simulate
from balustrade.dsl.sets import Box
from balustrade.dsl.system import LinearSystem
from balustrade.errors import BalustradeError
from balustrade.examples.pendulum import pendulum_terminal_cbf
from balustrade.models.pendulum import pendulum, pendulum_setup
from balustrade.problems.pcbf import pcbf_filter_problem, pcbf_slack_problem

N = 10
A = np.array([[1.0, 0.1], [-0.4, 0.85]])  # spectral radius 0.94
B = np.array([[0.0], [0.5]])
P = sla.solve_discrete_lyapunov(A.T, np.eye(2))
LEVEL = 0.125 / np.max(np.diag(np.linalg.inv(P)))
STARTS = ([0.5, -1.0], [-0.8, 0.6])
STEPS = 40


def _option(first: bool | None) -> dict:
    """``certificate_first`` as given, or not passed at all (``None``: the default)."""
    return {} if first is None else {"certificate_first": first}


def _linear(first: bool | None = None) -> tuple[LinearSystem, PCBFSafetyFilter]:
    system = LinearSystem(A, B, name="stable2")
    X, U = Box([-1.0, -1.5], [1.0, 1.5]), Box([-2.0], [2.0])
    ctl = PCBFSafetyFilter.build(system, X, U, lambda x: x.T @ P @ x - LEVEL, N,
                                 1e-3 * np.arange(N), target="real-time")
    return system, PCBFSafetyFilter(ctl.slack, ctl.filter, U, **_option(first))


def _pendulum(first: bool | None = None) -> tuple[object, PCBFSafetyFilter]:
    system, s = pendulum(), pendulum_setup()
    args = (system, s.X, s.U, pendulum_terminal_cbf(), s.N, s.deltas)
    slack = compile(pcbf_slack_problem(*args, alpha_f=s.alpha_f, slack_norm=1),
                    "structured-ip")
    filt = compile(pcbf_filter_problem(*args), "structured-ip")
    return system, PCBFSafetyFilter(slack, filt, s.U, **_option(first))


def _loops(system, ctl, low: float, high: float, shift: float, seed: int, steps: int):
    rng = np.random.default_rng(seed)
    runs = []
    for x0 in STARTS:
        proposals = rng.uniform(low, high, size=steps) + shift
        ctl.reset()
        runs.append(simulate(system, ctl, x0, steps, keep_infos=True,
                             proposal=lambda k, x, p=proposals: np.array([p[k]])))
    return runs


def _first(trace) -> list[int]:
    return [k for k, i in enumerate(trace.infos) if i.values.get("certificate_first")]


def _same_loops(runs_py, runs_c) -> int:
    """C = Python step by step; returns how many steps skipped (2.24) (in both)."""
    fired = 0
    for t1, t2 in zip(runs_py, runs_c):
        assert _first(t1) == _first(t2)
        fired += len(_first(t1))
        assert [i.status for i in t1.infos] == [i.status for i in t2.infos]
        assert t1.fallbacks == t2.fallbacks
        assert [i.uncertified for i in t1.infos] == [i.uncertified for i in t2.infos]
        for a, b in zip(t1.infos, t2.infos):
            assert sorted(a.values) == sorted(b.values)
            for key in a.values:
                np.testing.assert_allclose(b.values[key], a.values[key], atol=1e-6,
                                           equal_nan=True)
        assert np.abs(t1.inputs - t2.inputs).max() <= 1e-6
    return fired


def _skipped_steps_are_reported_certified(trace) -> None:
    """A skipped (2.24) is never a solver result: status "certified", its (2.24) point the
    candidate, a merely ``feasible`` point (solver "shifted_plan", 0 iterations) with
    h_PB = 0 and zero slacks."""
    for k in _first(trace):
        info = trace.infos[k]
        assert info.status.startswith("certified"), (k, info.status)
        assert "slack" not in info.uncertified
        cand = info.solutions["slack"]
        assert cand.status == "feasible" and cand.solver == "shifted_plan"
        assert cand.iterations == 0
        assert info.values["h_PB"] == 0.0
        assert np.all(np.asarray(cand["xi"]) == 0.0)


@pytest.fixture(scope="module")
def linear_c(tmp_path_factory):
    from balustrade.codegen import CPCBFSafetyFilter, build, emit_pcbf

    system, py = _linear()
    out = tmp_path_factory.mktemp("certfirst")
    emitted = emit_pcbf(py, "cfpcbf", out)
    lib = build(out, emitted.name, werror=True)
    return {"system": system, "py": py, "c": CPCBFSafetyFilter(lib), "emitted": emitted,
            "out": out}


def test_option_needs_the_certificate():
    """On by default (session 11, issue #14 "defaults must be right") wherever the
    certificate is; off by default without it (and then the filter runs as before: no
    step skips (2.24)); asked for explicitly without it, refused."""
    system, ctl = _linear()
    with pytest.raises(BalustradeError, match="shifted_certificate"):
        PCBFSafetyFilter(ctl.slack, ctl.filter, ctl.U, shifted_certificate=False,
                         certificate_first=True)
    assert PCBFSafetyFilter(ctl.slack, ctl.filter, ctl.U).certificate_first is True
    assert PCBFSafetyFilter.build(system, Box([-1.0, -1.5], [1.0, 1.5]), ctl.U,
                                  lambda x: x.T @ P @ x - LEVEL, N, 1e-3 * np.arange(N),
                                  target="real-time").certificate_first is True
    bare = PCBFSafetyFilter(ctl.slack, ctl.filter, ctl.U, shifted_certificate=False)
    assert bare.certificate_first is False
    assert bare.deployment_spec().certificate_first is False
    runs = _loops(system, bare, -3.0, 3.0, 1.5, 7, 15)
    assert not any(_first(t) for t in runs)
    assert not any(i.status.startswith("certified") for t in runs for i in t.infos)


def test_spec_manifest_and_config_carry_the_option(linear_c, tmp_path):
    from balustrade.codegen import emit_pcbf

    assert linear_c["py"].deployment_spec().certificate_first is True
    assert linear_c["emitted"].manifest["certificate_first"] is True
    assert linear_c["c"].certificate_first
    assert "#define cfpcbf_CERT_FIRST 1" in (linear_c["out"] / "cfpcbf_config.h").read_text()
    _, off = _linear(first=False)
    emitted = emit_pcbf(off.deployment_spec(), "cfoff", tmp_path)
    assert emitted.manifest["certificate_first"] is False
    assert "#define cfoff_CERT_FIRST 0" in (tmp_path / "cfoff_config.h").read_text()


def test_linear_c_equals_python_where_it_fires_and_where_not(linear_c):
    """Loops that start outside S_PB (``ξ* > 0``: the shifted plan certifies nothing, (2.24)
    is solved) and then skip it: the same steps skip in C and Python, the same statuses,
    values and inputs. Fails if the C does not skip (no ``certificate_first`` value) or
    skips elsewhere."""
    system = linear_c["system"]
    runs_py = _loops(system, linear_c["py"], -3.0, 3.0, 1.5, 7, STEPS)
    runs_c = _loops(system, linear_c["c"], -3.0, 3.0, 1.5, 7, STEPS)
    fired = _same_loops(runs_py, runs_c)
    solved = sum(len(t.infos) - len(_first(t)) for t in runs_py)
    assert fired >= 5 and solved >= 2, (fired, solved)
    for t in runs_py:
        _skipped_steps_are_reported_certified(t)


def test_linear_c_equals_python_with_the_option_off(tmp_path):
    """``certificate_first=False`` (explicit, no longer the default): the same loops as
    above, every (2.24) solved in C and in Python, the same statuses (``"ok"``, never
    ``"certified"``), values and inputs. Fails if the off path skips anywhere or C and
    Python part."""
    from balustrade.codegen import CPCBFSafetyFilter, build, emit_pcbf

    system, off = _linear(first=False)
    emitted = emit_pcbf(off, "cfoff", tmp_path)
    c_off = CPCBFSafetyFilter(build(tmp_path, emitted.name, werror=True))
    assert not c_off.certificate_first
    runs_py = _loops(system, off, -3.0, 3.0, 1.5, 7, STEPS)
    runs_c = _loops(system, c_off, -3.0, 3.0, 1.5, 7, STEPS)
    assert _same_loops(runs_py, runs_c) == 0
    statuses = {i.status for t in runs_py for i in t.infos}
    assert "ok" in statuses and not any(st.startswith("certified") for st in statuses)


def test_skip_only_when_the_candidate_meets_every_row():
    """Negative control: at every step of a loop the decision equals an independent check
    of the candidate (largest row violation <= tol with zero slack); a plan whose roll-out
    leaves X (it would need a positive slack) is never skipped: (2.24) is solved. Fails if
    the skip ignores the rows."""
    system, ctl = _linear()
    cert = ctl.certificate
    ctl.reset()
    rng = np.random.default_rng(7)
    x = np.array(STARTS[0])
    decisions = []
    for k in range(STEPS):
        expect = False
        if ctl._plan is not None:
            U = cert.padded(ctl._plan[:, ctl._plan_age + 1:])
            _, violation, cost = cert.function().call([x, U])
            expect = float(violation) <= cert.tol and abs(float(cost)) <= cert.zero_tol
        u, info = ctl.step(x, np.array([rng.uniform(-3.0, 3.0) + 1.5]))
        assert bool(info.values.get("certificate_first")) == expect, k
        decisions.append(expect)
        x = system.step(x, u)
    assert any(decisions) and not all(decisions)
    # a plan that drives the state out of X: its shifted candidate needs a positive slack
    ctl._plan, ctl._plan_age = np.full((1, N), 2.0), 0
    bad_U = cert.padded(ctl._plan[:, 1:])
    assert float(cert.function().call([x, bad_U])[1]) > 1e-3
    u, info = ctl.step(x, np.array([0.0]))
    assert "certificate_first" not in info.values
    assert info.solutions["slack"].solver != "shifted_plan"


@pytest.fixture(scope="module")
def pendulum_c(tmp_path_factory):
    from balustrade.codegen import accelerate

    system, py = _pendulum()
    c = accelerate(py, build_dir=tmp_path_factory.mktemp("cfpend"), name="cfpend",
                   werror=True)
    return system, py, c


def test_pendulum_staged_c_equals_python(pendulum_c):
    """The pendulum pair on fatrop (stage-ordered C): the skipped steps, statuses and
    inputs agree, and the certified steps are reported as such."""
    system, py, c = pendulum_c
    runs_py = _loops(system, py, -4.0, 4.0, 0.0, 3, 30)
    runs_c = _loops(system, c, -4.0, 4.0, 0.0, 3, 30)
    fired = _same_loops(runs_py, runs_c)
    assert fired >= 5
    for t in runs_py:
        _skipped_steps_are_reported_certified(t)


@pytest.fixture(scope="module")
def cartpole_c(tmp_path_factory):
    from balustrade.codegen import accelerate
    from balustrade.examples.cartpole import cartpole_design, cartpole_problems

    d = cartpole_design()
    py = PCBFSafetyFilter(*cartpole_problems("structured-ip", design=d), d.U)  # default: on
    assert py.certificate_first
    c = accelerate(py, build_dir=tmp_path_factory.mktemp("cfcart"), name="cfcart",
                   werror=True)
    return d, py, c


@pytest.mark.slow
def test_cartpole_closed_loop_c_equals_python(cartpole_c):
    """The cart-pole scenario (100 steps): the C step at every state of the Python loop
    makes the same decisions (skip or solve) with the same inputs; no failure, X kept."""
    from balustrade.examples.cartpole import cartpole_scenario

    d, py, c = cartpole_c
    x, proposal = cartpole_scenario()
    py.reset()
    c.reset()
    fired = 0
    for k in range(100):
        u_p = proposal(x, k)
        (u, i_py), (u_c, i_c) = py.step(x, u_p), c.step(x, u_p)
        assert (i_py.status, i_py.fallback, i_py.uncertified) == \
            (i_c.status, i_c.fallback, i_c.uncertified), k
        assert i_py.status in ("ok", "certified") and not i_py.fallback, (k, i_py)
        fired += bool(i_py.values.get("certificate_first"))
        np.testing.assert_allclose(i_c.values["h_PB"], i_py.values["h_PB"], atol=1e-6)
        np.testing.assert_allclose(u_c, u, atol=1e-6)
        x = d.system.step(x, u)
        assert np.all(np.abs(x) <= d.X.h[:4] + 1e-9), (k, x)
    assert fired >= 50


DRIVER = r"""
#include <stdio.h>
#include "cfpend.h"
#include "replay.h"

int main(void) {
  cfpend_work* wk = cfpend_alloc();
  casadi_real u[cfpend_NU], h;
  int k, st, fired = 0;
  if (!wk) return 1;
  for (k = 0; k < REPLAY_K; ++k) {
    cfpend_step(REPLAY_X[k], REPLAY_U + k, u, &h, &st, wk);
    fired += cfpend_cert_first(wk);
    printf("%d %.17g\n", st, u[0]);
  }
  printf("fired %d\n", fired);
  cfpend_free(wk);
  return 0;
}
"""


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("valgrind") is None, reason="needs valgrind")
def test_replayed_loop_is_memory_clean_under_valgrind(pendulum_c):
    """A pendulum loop that skips (2.24) replayed through the C step by a driver without
    Python, under valgrind: no memory error, no leak, the same inputs and skips."""
    from balustrade.codegen import build_executable

    system, py, c = pendulum_c
    trace = _loops(system, py, -4.0, 4.0, 0.0, 3, 30)[0]
    assert _first(trace)
    out = c.accelerated["dir"]
    steps = len(trace.infos)
    rows = ",\n".join("{" + ", ".join(f"{v:.17g}" for v in r) + "}"
                      for r in np.asarray(trace.states)[:steps])
    props = np.random.default_rng(3).uniform(-4.0, 4.0, size=steps)
    (out / "replay.h").write_text(
        f"#define REPLAY_K {steps}\nstatic const casadi_real REPLAY_X[{steps}][2] = "
        f"{{{rows}}};\nstatic const casadi_real REPLAY_U[{steps}] = "
        f"{{{', '.join(f'{v:.17g}' for v in props)}}};\n")
    (out / "driver.c").write_text(DRIVER)
    exe = build_executable(out, main="driver.c", werror=True,
                           extra_flags=tuple(c._lib.manifest["link_flags"]))
    proc = run_under_valgrind(str(exe), timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = proc.stdout.splitlines()
    assert lines[-1] == f"fired {len(_first(trace))}"
    u_c = np.array([float(line.split()[1]) for line in lines[:-1]])
    assert np.abs(u_c - np.asarray(trace.inputs).reshape(-1)).max() <= 1e-6


def test_build_passes_the_certificate_options():
    """``PCBFSafetyFilter.build`` passes ``certificate_first``, ``shifted_certificate`` and
    ``warm_start`` to the constructor (it could not set them before)."""
    system = LinearSystem(A, B, name="stable2")
    X, U = Box([-1.0, -1.5], [1.0, 1.5]), Box([-2.0], [2.0])
    args = (system, X, U, lambda x: x.T @ P @ x - LEVEL, N, 1e-3 * np.arange(N))
    off = PCBFSafetyFilter.build(*args, target="real-time", certificate_first=False,
                                 warm_start="shifted")
    assert off.certificate_first is False and off.certificate is not None
    assert off.warm_start == "shifted"
    assert not any(_first(t) for t in _loops(system, off, -3.0, 3.0, 1.5, 7, 15))
    bare = PCBFSafetyFilter.build(*args, target="real-time", shifted_certificate=False)
    assert bare.certificate is None and bare.certificate_first is False
    with pytest.raises(BalustradeError, match="shifted_certificate"):
        PCBFSafetyFilter.build(*args, target="real-time", shifted_certificate=False,
                               certificate_first=True)
