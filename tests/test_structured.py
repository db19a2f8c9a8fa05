"""The stage-ordered lowering (backends/passes/stage_order.py) and the structured targets
``structured-ip`` (fatrop) and ``structured-sqp`` (sqpmethod + HPIPM), issue #14 §2."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from balustrade.backends import compile
from balustrade.backends.passes import CASADI_CHAIN, run_chain
from balustrade.backends.passes.stage_order import StructureError, stage_order
from balustrade.dsl import OCP, Box, LinearSystem, squared_norm, sum_norms
from balustrade.examples.pendulum import pendulum_terminal_cbf
from balustrade.models.pendulum import pendulum, pendulum_setup
from balustrade.problems.pcbf import extended_pcbf_problem, pcbf_slack_problem

STRUCTURED = ("structured-ip", "structured-sqp")


def _agree(ocp, states, rtol=1e-5, atol=1e-6, targets=STRUCTURED):
    """Both say optimal → same optimal value; returns the number of compared solves."""
    exact = compile(ocp, "exact")
    compared = 0
    for tgt in targets:
        c = compile(ocp, tgt)
        for par in states:
            a, b = exact.solve(par), c.solve(par)
            if a.success and b.success:
                assert b.objective == pytest.approx(a.objective, rel=rtol, abs=atol), (tgt, par)
                assert set(b.primal) == set(a.primal)
                for name, val in a.primal.items():
                    assert np.shape(b.primal[name]) == np.shape(val)
                compared += 1
    return compared


@pytest.fixture(scope="module")
def pend():
    system, s = pendulum(), pendulum_setup()
    return (system, s.X, s.U, pendulum_terminal_cbf(), s.N, s.deltas), s


PEND_STATES = [{"x0": x} for x in ([0.1, 0.2], [0.5, -0.3], [1.0, 1.0], [-0.8, 0.6])]


@pytest.mark.parametrize("norm", [1, np.inf])
def test_pendulum_slack_problem_agrees(pend, norm):
    args, s = pend
    ocp = pcbf_slack_problem(*args, alpha_f=s.alpha_f, slack_norm=norm)
    assert _agree(ocp, PEND_STATES) >= 6


def test_pendulum_extended_problem_agrees(pend):
    args, _ = pend
    assert _agree(extended_pcbf_problem(*args), PEND_STATES) >= 6


def test_structured_solution_is_in_the_layouts_terms(pend):
    """Primal blocks, row duals and bound duals come back in the OCP's layout."""
    args, s = pend
    ocp = pcbf_slack_problem(*args, alpha_f=s.alpha_f, slack_norm=1)
    a = compile(ocp, "exact").solve(PEND_STATES[2])
    b = compile(ocp, "structured-sqp").solve(PEND_STATES[2])
    assert b.success and b.solver == "sqpmethod"
    # the LP-like (2.24) has many minimizers: compare what is unique
    np.testing.assert_allclose(b.primal["x"][:, 0], [1.0, 1.0], atol=1e-9)
    np.testing.assert_allclose(b.primal["xi_N"], a.primal["xi_N"], atol=1e-7)
    assert set(b.dual) == set(a.dual)
    for key, val in a.dual.items():
        assert np.shape(b.dual[key]) == np.shape(val), key
    # the initial-state multiplier is the sensitivity of h_PB to x0: unique
    np.testing.assert_allclose(b.dual["initial_state"], a.dual["initial_state"], rtol=1e-4,
                               atol=1e-3)


def test_structured_warm_start_round_trips(pend):
    args, s = pend
    c = compile(extended_pcbf_problem(*args), "structured-ip")
    first = c.solve(PEND_STATES[1])
    again = c.solve(PEND_STATES[1], warm_start=first)
    assert again.success and again.objective == pytest.approx(first.objective, abs=1e-7)
    from_dict = c.solve(PEND_STATES[1], warm_start=dict(first.primal))
    assert from_dict.success


def test_small_rendezvous_515_agrees():
    from balustrade.problems.robust import robust_pcbf_slack_problem
    from balustrade.reproduce.rendezvous import design

    d = design(10, 20)
    sys, s, err, cbf = d["system"], d["setup"], d["error"], d["cbf"]
    ocp = robust_pcbf_slack_problem(sys, s.X, s.U, cbf, s.N, s.deltas(), err, s.alpha_f)
    rng = np.random.default_rng(0)
    states = [{"x0": np.concatenate([rng.uniform(-9, 9, 3), rng.uniform(-4, 4, 3)])}
              for _ in range(3)]
    assert _agree(ocp, states, rtol=1e-4, atol=1e-5) >= 3


def test_bicycle_515_agrees():
    from balustrade.examples.bicycle import bicycle_design
    from balustrade.problems.robust import robust_pcbf_slack_problem

    d = bicycle_design(N=8)
    ocp = robust_pcbf_slack_problem(d.system, d.X, d.U, d.cbf, d.N, d.deltas, d.error,
                                    d.alpha_f)
    states = [{"x0": np.array(x)} for x in ([0.1, 0.1, 1.0, 0.0], [0.25, -0.4, 0.8, 0.3])]
    assert _agree(ocp, states, rtol=1e-4, atol=1e-5, targets=("structured-sqp",)) >= 2


def _fatrop_first(ocp, states, atol=1e-6):
    """structured-ip's first attempt (fatrop itself, no retry) against ``exact``: every
    state optimal on both, objectives within ``atol`` (fatrop relaxes bounds by 1e-8
    relative; the backend projects onto them)."""

    exact = compile(ocp, "exact")
    fatrop = compile(ocp, "structured-ip-noretry")
    for par in states:
        a, b = exact.solve(par), fatrop.solve(par)
        assert a.success and b.success and b.solver == "fatrop", (par, b.message)
        assert b.objective == pytest.approx(a.objective, abs=atol), par


def test_fatrop_on_the_nonlinear_bicycle_515_agrees():
    """The nonlinear bicycle (5.15) with fatrop (the refusal of nonlinear dynamics is
    lifted: no hang in 120 states, N = 5, 8, 20; docs/engines.md)."""
    from balustrade.examples.bicycle import bicycle_design
    from balustrade.problems.robust import robust_pcbf_slack_problem

    d = bicycle_design(N=8)
    ocp = robust_pcbf_slack_problem(d.system, d.X, d.U, d.cbf, d.N, d.deltas, d.error,
                                    d.alpha_f)
    # states on which fatrop itself converges (on others it stops with return flag 1 and
    # the IPOPT retry answers: test_structured_ip_failure_is_honest)
    _fatrop_first(ocp, [{"x0": np.array(x)} for x in
                        ([0.1, 0.1, 1.0, 0.0], [0.25, -0.4, 0.8, 0.3])])


def test_fatrop_on_the_cartpole_pair_agrees():
    """(2.24) and (2.23) of the cart-pole (RK4, N = 20) with fatrop."""
    from balustrade.examples.cartpole import cartpole_design
    from balustrade.problems.pcbf import pcbf_filter_problem

    d = cartpole_design()
    args = (d.system, d.X, d.U, d.h_f, d.N, d.deltas)
    slack = pcbf_slack_problem(*args, alpha_f=d.alpha_f, slack_norm=1)
    states = [{"x0": np.array(x)} for x in ([0.0, 0.15, 0.0, 0.0], [-0.25, 0.0066, 1.17, 1.1],
                                           [0.3, 0.2, 0.4, -0.4])]
    _fatrop_first(slack, states)
    exact = compile(slack, "exact")
    params = []
    for par in states:
        s = exact.solve(par)
        params.append({**par, "u_p": np.array([8.0]), "xi": s.primal["xi"],
                       "xi_N": s.primal["xi_N"]})
    # (2.23) at the second state: fatrop's optimum is 4e-6 below exact's (u_0 differs by
    # 1e-6) with any fatrop tol down to 1e-12 — its bound relaxation (1e-8 relative, no
    # option) loosens the active tightened rows; hence 1e-5 here
    _fatrop_first(pcbf_filter_problem(*args), params, atol=1e-5)


@pytest.mark.parametrize("norm", [1, np.inf])
def test_fatrop_on_the_lane_keeping_agrees(norm):
    from balustrade.examples.bicycle import bicycle_design

    d = bicycle_design(N=10)
    ocp = pcbf_slack_problem(d.system, d.X, d.U, d.cbf, 10, 1e-4 * np.arange(10), d.alpha_f,
                             norm)
    _fatrop_first(ocp, [{"x0": np.array(x)} for x in
                        ([0.0071, 0.629, 0.7009, 0.4698], [0.15, -0.31, 0.94, 0.5])])


def test_structured_ip_failure_is_honest():
    """fatrop's return flag decides the status: at its iteration limit the run is never
    optimal (here: primal feasible, so ``feasible``) and the default chain's IPOPT retry
    answers and says so; stopped at fatrop's acceptable point it is not a success either
    (the emitted C cannot tell that stop from a failure: Python reads it the same way,
    tests/test_status_mapping.py): ``feasible``, its point primal feasible."""
    from balustrade.examples.bicycle import bicycle_design
    from balustrade.problems.robust import robust_pcbf_slack_problem

    d = bicycle_design(N=8)
    ocp = robust_pcbf_slack_problem(d.system, d.X, d.U, d.cbf, d.N, d.deltas, d.error,
                                    d.alpha_f)
    exact, alone = compile(ocp, "exact"), compile(ocp, "structured-ip-noretry")
    par = {"x0": np.array([0.18796214352016344, 0.576315506357291, 1.024645043037026,
                           0.2403282366704838])}
    stopped = alone.solve(par)
    assert not stopped.success and stopped.status != "optimal"
    assert "MaxIterExceeded" in stopped.message
    chained = compile(ocp, "structured-ip").solve(par)
    assert chained.success and chained.solver == "ipopt" and "after retries" in chained.message
    assert chained.objective == pytest.approx(exact.solve(par).objective, rel=1e-6)
    par = {"x0": np.array([0.0692310668887523, -0.16241677376820635, 1.2980469550524476,
                           0.5035295892952546])}
    acceptable = alone.solve(par)
    assert acceptable.status == "feasible" and not acceptable.success
    assert "StopAtAcceptablePoint" in acceptable.message
    assert acceptable.objective == pytest.approx(exact.solve(par).objective, abs=1e-6)


# -- the pass itself ------------------------------------------------------------------------
def _random_ocp(nx: int, nu: int, N: int, extras: int, norm: float) -> OCP:
    rng = np.random.default_rng(nx * 100 + nu * 10 + N)
    A = np.eye(nx) + 0.1 * rng.standard_normal((nx, nx))
    B = rng.standard_normal((nx, nu))
    system = LinearSystem(A, B)
    ocp = OCP(system, N, name="staged_ocp")
    ocp.initial_state(ocp.parameter("x0", nx))
    ocp.dynamics()
    ocp.input_constraint(Box([-1.0] * nu, [1.0] * nu))
    xi = ocp.state_constraint(Box([-2.0] * nx, [2.0] * nx), slack="variable")
    # a separable row over all stages with a constant part, like (6.15g)
    ocp.decrease(ca.sum1(ca.sum2(xi)) + ca.sumsqr(ocp.x), ocp.parameter("bound", 1) + 3.0)
    cost = sum_norms(xi, norm) + squared_norm(ocp.u)
    for k in range(extras):
        t = ocp.variable(f"t{k}", 1, lb=-5.0, ub=5.0)
        ocp.le(ocp.x[0, N] - t, name=f"ext{k}")
        cost = cost + squared_norm(t)
    ocp.minimize(cost)
    return ocp


@settings(max_examples=12, deadline=None)
@given(nx=st.integers(1, 3), nu=st.integers(1, 2), N=st.integers(2, 6),
       extras=st.integers(0, 2), norm=st.sampled_from([1, 2, np.inf]))
def test_stage_order_round_trips(nx, nu, N, extras, norm):
    """``take`` is injective and ``primal(staged(w)) == w`` for any point; the staged
    problem has the same cost and rows at lifted points (copies and running sums)."""
    ocp = _random_ocp(nx, nu, N, extras, norm)
    data, _ = run_chain(CASADI_CHAIN, ocp)
    staged, inv = stage_order(ocp, data)
    n = data.lbx.size
    assert len(set(inv.take.tolist())) == n
    assert sum(staged.nx) + sum(staged.nu) == staged.lbx.size
    assert sum(staged.ng) + sum(staged.nx[1:]) == staged.lbg.size
    rng = np.random.default_rng(N)
    w, p = rng.standard_normal(n), rng.standard_normal(data.nlp["p"].numel())
    ws = inv.staged(w, p)
    np.testing.assert_allclose(inv.primal(ws), w)
    f0 = ca.Function("f0", [data.nlp["x"], data.nlp["p"]], [data.nlp["f"], data.nlp["g"]])
    f1 = ca.Function("f1", [staged.nlp["x"], staged.nlp["p"]],
                     [staged.nlp["f"], staged.nlp["g"]])
    (fa, ga), (fb, gb) = f0(w, p), f1(ws, p)
    assert float(fb) == pytest.approx(float(fa), rel=1e-9, abs=1e-9)
    ga, gb = np.asarray(ga).ravel(), np.asarray(gb).ravel()
    np.testing.assert_allclose(gb[inv.row_take], ga, rtol=1e-9, atol=1e-9)
    others = np.setdiff1d(np.arange(gb.size), inv.row_take)
    np.testing.assert_allclose(gb[others], 0.0, atol=1e-9)  # gaps, copies, sums hold


def test_refuses_a_rate_cost_naming_the_cost():
    ocp = _random_ocp(2, 1, 4, 0, 1)
    ocp.minimize(squared_norm(ocp.u[:, 1:] - ocp.u[:, :-1]))
    with pytest.raises(StructureError, match="the cost"):
        compile(ocp, "structured-ip")


def test_refuses_a_nonseparable_row_naming_the_block():
    ocp = _random_ocp(2, 1, 4, 0, 1)
    ocp.le(ocp.x[0, 0] * ocp.x[0, 4], 1.0, name="coupling")
    with pytest.raises(StructureError, match="coupling"):
        compile(ocp, "structured-sqp")


@pytest.mark.parametrize("coupling", [
    lambda u: ca.sign(u[0, 1] - u[0, 0]),
    lambda u: ca.if_else(u[0, 1] > 0, u[0, 0], 0.0),
])
def test_refuses_a_coupling_the_hessian_cannot_see(coupling):
    """A row coupling two stages through a piecewise constant function has no cross-stage
    Hessian entry; split by stage it would become another row (sign(u1 − u0) is not
    sign(u1) − sign(u0)): refused, not silently changed."""
    ocp = _random_ocp(2, 1, 4, 0, 1)
    ocp.le(coupling(ocp.u) - 0.5, 0.0, name="jump")
    data, _ = run_chain(CASADI_CHAIN, ocp)
    with pytest.raises(StructureError, match="'jump'.*not additively separable"):
        stage_order(ocp, data)


def test_refuses_a_scaled_dynamics_row_naming_the_block():
    """``2·(x_(k+1) − A x_k − B u_k) = 0`` tagged dynamics: fatrop and HPIPM take the gap
    rows' block on ``x_(k+1)`` as the identity (fatrop errored, the SQP stalled, and only
    the IPOPT retry answered); refused at compile time instead."""
    A, B = np.array([[1.0, 0.1], [0.0, 1.0]]), np.array([[0.0], [0.1]])
    ocp = OCP(LinearSystem(A, B), 4, name="scaled_dynamics")
    ocp.initial_state(ocp.parameter("x0", 2))
    x, u = ocp.x, ocp.u
    ocp.eq(2.0 * (x[:, 1:] - (A @ x[:, :-1] + B @ u)), 0, name="dyn2", tag="dynamics")
    ocp.minimize(squared_norm(x) + squared_norm(u))
    for tgt in STRUCTURED:
        with pytest.raises(StructureError, match="'dyn2'.*coefficient 1"):
            compile(ocp, tgt)


def test_refuses_an_ocp_without_horizon():
    ocp = OCP(name="static")
    y = ocp.variable("y", 2)
    ocp.minimize(squared_norm(y))
    with pytest.raises(StructureError, match="horizon"):
        compile(ocp, "structured-ip")


# -- C: the emitted solvers link with the libraries of the casadi wheel ---------------------
@pytest.mark.skipif(shutil.which("gcc") is None, reason="needs gcc")
@pytest.mark.parametrize("name", STRUCTURED)
def test_structured_c_compiles_and_links(tmp_path: Path, name):
    from balustrade.backends import resolve_target

    ocp = _random_ocp(2, 1, 3, 0, 1)
    c = compile(ocp, name)
    tgt = resolve_target(name)
    assert tgt.emit_reason() is not None  # external libraries: refused by default
    assert tgt.emit_reason(allow_external=True) is None
    libs = tgt.c_libraries()
    assert "blasfeo" in libs and ("fatrop" in libs or "hpipm" in libs)
    cdir = Path(ca.__file__).parent
    src = tmp_path / "nlp.c"
    c.solver.generate("nlp.c", {"with_header": False})
    Path("nlp.c").replace(src)
    cmd = ["gcc", "-shared", "-fPIC", "-O0", "-o", str(tmp_path / "libnlp.so"), str(src),
           f"-I{cdir / 'include'}", f"-I{cdir / 'include' / 'fatrop'}", f"-L{cdir}",
           f"-Wl,-rpath,{cdir}", *[f"-l{lib}" for lib in libs], "-lm"]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]


def test_balustrade_emitter_refuses_a_staged_problem(tmp_path: Path):
    """codegen.emit_problem unpacks the layout order; a staged problem is refused, not
    emitted with wrong offsets."""
    from balustrade.codegen.emit import emit_problem
    from balustrade.errors import CodegenError

    c = compile(_random_ocp(2, 1, 3, 0, 1), "structured-sqp")
    with pytest.raises(CodegenError, match="stage order"):
        emit_problem(c, "staged", tmp_path, allow_external=True)


def test_fatrop_refuses_a_2norm_cost_instead_of_hanging():
    """structured-ip on a cost with a 2-norm term: a StructureError naming the term and the
    targets to use, at compile time (there a fatrop solve looped forever; docs/engines.md)."""
    from balustrade.examples.bicycle import bicycle_design

    d = bicycle_design(N=5)
    ocp = pcbf_slack_problem(d.system, d.X, d.U, d.cbf, 5, 1e-4 * np.arange(5), d.alpha_f, 2)
    with pytest.raises(StructureError, match="2-norm term.*loop forever.*long-horizon"):
        compile(ocp, "structured-ip")


_HANG_SCRIPT = """
import numpy as np
from balustrade.backends import compile
from balustrade.backends.passes.stage_order import StructureError
from balustrade.examples.bicycle import bicycle_design
from balustrade.problems.pcbf import pcbf_slack_problem

d = bicycle_design(N=5)
ocp = pcbf_slack_problem(d.system, d.X, d.U, d.cbf, 5, 1e-4 * np.arange(5), d.alpha_f, 2)
try:
    c = compile(ocp, "structured-ip")
except StructureError:
    print("refused")
else:
    print(c.solve({"x0": np.array([0.0071, 0.629, 0.7009, 0.4698])}).status)
"""


def test_the_fatrop_hang_case_returns(tmp_path: Path):
    """The state on which a fatrop solve of the lane-keeping (2.24) with the 2-norm slack cost
    never returned (N = 5; tested in a subprocess with a time limit, so a regression cannot
    hang the test run): structured-ip now returns at once (refused)."""
    import os
    import sys

    script = tmp_path / "hang.py"
    script.write_text(_HANG_SCRIPT)
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    try:
        out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                             timeout=60, env=env)
    except subprocess.TimeoutExpired:
        pytest.fail("structured-ip on the 2-norm lane-keeping did not return within 60 s")
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "refused"
