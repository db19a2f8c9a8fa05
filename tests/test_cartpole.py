"""The cart-pole model and PCBF example (issue #14, nonlinear case) and the shared
derivative functions of sqpmethod (backends.casadi_backend.shared_derivatives).

Fast: model sanity (energy, linearization), the sharing (one Hessian in the C of a problem
with retries; Python and its retry solvers agree), a short filtered closed loop.
Slow: the 100-step closed loop, the emitted C built with -Werror, C = Python on states."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from balustrade.backends.casadi_backend import shared_derivatives
from balustrade.control import PCBFSafetyFilter
from balustrade.examples.cartpole import (
    X0,
    cartpole_design,
    cartpole_problems,
    destabilizing_proposal,
)
from balustrade.models.cartpole import (
    CART_MASS,
    GRAVITY,
    LENGTH,
    POLE_MASS,
    TS,
    cartpole,
    cartpole_ct,
    cartpole_energy,
    cartpole_setup,
)

LIMITS = np.array([1.0, 0.35, 2.0, 3.0])


@pytest.fixture(scope="module")
def design():
    return cartpole_design()


@pytest.fixture(scope="module")
def problems(design):
    return cartpole_problems("fast-sqp", design=design)


def test_energy_is_conserved_without_force():
    system = cartpole()
    x = np.array([0.1, 0.2, -0.3, 0.5])
    e0 = cartpole_energy(x)
    for _ in range(10):  # 0.5 s of RK4, the pole falls to 1.4 rad: drift 1.6e-5
        x = system.step(x, [0.0])
    assert abs(cartpole_energy(x) - e0) < 5e-5 * abs(e0)  # a wrong mass: 3e-3


def test_linearization_matches_the_textbook_model():
    """At the upright equilibrium: p̈ = (F − m g θ)/M, θ̈ = ((M+m) g θ − F)/(l M)."""
    x, u = ca.SX.sym("x", 4), ca.SX.sym("u", 1)
    rhs = cartpole_ct()(x, u)
    jac = ca.Function("j", [x, u], [ca.jacobian(rhs, x), ca.jacobian(rhs, u)])
    Ac, Bc = (np.asarray(m) for m in jac(np.zeros(4), np.zeros(1)))
    M, m, l, g = CART_MASS, POLE_MASS, LENGTH, GRAVITY
    expect_A = np.zeros((4, 4))
    expect_A[0, 2] = expect_A[1, 3] = 1.0
    expect_A[2, 1] = -m * g / M
    expect_A[3, 1] = (M + m) * g / (l * M)
    np.testing.assert_allclose(Ac, expect_A, atol=1e-12)
    np.testing.assert_allclose(Bc.ravel(), [0, 0, 1 / M, -1 / (l * M)], atol=1e-12)
    A, _ = cartpole().jacobians(np.zeros(4), np.zeros(1))
    np.testing.assert_allclose(A, np.eye(4) + TS * Ac, atol=0.05)  # RK4 ≈ Euler + O(T_s²)
    assert np.max(np.abs(np.linalg.eigvals(A))) > 1.2  # the upright pole is unstable


def test_setup_and_terminal_cbf(design):
    s = cartpole_setup()
    assert s.N == 20 and s.deltas[-1] == pytest.approx(19e-4)
    assert design.h_f.gamma_f > 0.1  # the reserve level keeps D_f larger than S_f
    assert design.h_f(np.zeros(4)) < 0


def test_unfiltered_proposal_leaves_the_constraints(design):
    x = X0.copy()
    for k in range(10):
        x = design.system.step(x, np.clip(destabilizing_proposal(x, k), -10, 10))
        if np.any(np.abs(x) > LIMITS):
            return
    pytest.fail("the destabilizing proposal should leave X within 10 steps")


def test_retry_solvers_share_the_derivative_functions(problems):
    slack, _ = problems
    shared = slack.derivatives
    assert set(shared) == {"jac_fg", "hess_lag", "cache"}
    retry = slack._retry_solvers()[0]  # the other convexification: same NLP, same functions
    p = [0.0, 0.15, 0.0, 0.0]
    args = dict(x0=0, p=p, lbx=slack.lbx, ubx=slack.ubx, lbg=slack.lbg, ubg=slack.ubg)
    a, b = slack.solver(**args), retry(**args)
    assert slack.solver.stats()["success"] and retry.stats()["success"]
    assert float(a["f"]) == pytest.approx(float(b["f"]), abs=1e-8)
    # the shared functions are what sqpmethod derives itself
    own = ca.nlpsol("own", "sqpmethod", slack.nlp, slack.options)(**args)
    np.testing.assert_allclose(np.asarray(a["x"]), np.asarray(own["x"]), atol=1e-9)
    assert shared_derivatives(slack.nlp, "ipopt", {}) == {}


def test_emitted_c_holds_one_copy_of_each_derivative(problems, tmp_path):
    """Before the sharing each retry solver carried its own Hessian (4.5 MB for the pair)."""
    from balustrade.codegen import emit_problem

    slack, _ = problems
    emitted = emit_problem(slack, "cps", tmp_path)
    text = (tmp_path / "cps_casadi.c").read_text()
    for fn in ("nlp_hess_l", "nlp_jac_fg", "nlp_fg", "nlp_grad"):
        assert text.count(f"/* {fn}:") == 1, fn
    assert len(emitted.manifest["problems"]["problem"]["retries"]) >= 1


def _closed_loop(filt: PCBFSafetyFilter, system, steps: int):
    x, infos = X0.copy(), []
    for k in range(steps):
        u, info = filt.step(x, destabilizing_proposal(x, k))
        infos.append(info)
        x = system.step(x, u)
        assert np.all(np.abs(x) <= LIMITS + 1e-9), (k, x)
    return x, infos


def test_filtered_closed_loop_keeps_the_constraints(design, problems):
    filt = PCBFSafetyFilter(*problems, design.U)
    _, infos = _closed_loop(filt, design.system, 5)
    assert all(i.values.get("h_PB", 1.0) <= 1e-6 for i in infos)


@pytest.mark.slow
def test_filtered_closed_loop_100_steps(design, problems):
    filt = PCBFSafetyFilter(*problems, design.U)
    _, infos = _closed_loop(filt, design.system, 100)
    assert all(i.fallback != "projected_proposal" for i in infos)


@pytest.fixture(scope="module")
def c_filter(design, problems, tmp_path_factory):
    from balustrade.codegen import CPCBFSafetyFilter, build, emit_pcbf

    out = tmp_path_factory.mktemp("cartpole_c")
    py = PCBFSafetyFilter(*problems, design.U)
    emitted = emit_pcbf(py, "cartpole", out)
    return py, CPCBFSafetyFilter(build(out, emitted.name, werror=True))


def _c_equals_python(design, c_filter, n: int) -> None:
    py, c = c_filter
    rng = np.random.default_rng(0)
    states = design.X.sample(n, rng) * 0.5
    compared = 0
    for x in states:
        u_p = destabilizing_proposal(x, 0)
        py.reset()
        c.reset()
        u_py, i_py = py.step(x, u_p)
        u_c, i_c = c.step(x, u_p)
        if i_py.status == "ok" and i_c.status == "ok":
            compared += 1
            np.testing.assert_allclose(u_c, u_py, atol=1e-6)
    # not every state is compared: where qrqp fails, Python's retry chain ends with IPOPT
    # and the C (no IPOPT) falls back (bench_cartpole counts these; issue #14 open)
    assert compared >= 1


@pytest.mark.slow
def test_c_equals_python_on_50_states(design, c_filter):
    _c_equals_python(design, c_filter, 50)


@pytest.mark.slow
def test_c_equals_python_on_1000_states(design, c_filter):
    _c_equals_python(design, c_filter, 1000)
