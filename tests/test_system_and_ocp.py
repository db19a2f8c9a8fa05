"""The language: systems from callables, sympy and continuous time; the OCP builder; the
terminal CBF SDP (7.11) against its own LMIs; compile-once re-solves with warm starts."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
import scipy.linalg
import sympy

from balustrade.backends import compile
from balustrade.design.terminal_cbf import synthesize_terminal_cbf
from balustrade.dsl import OCP, Box, Ellipsoid, LinearSystem, System, norm, sum_norms
from balustrade.problems.terminal_cbf import largest_level
from balustrade.testing import compare_backends, verify


def test_callable_sympy_and_linear_systems_agree():
    A = np.array([[1.0, 0.1], [0.2, 0.9]])
    B = np.array([[0.0], [0.1]])
    lin = LinearSystem(A, B)
    call = System(lambda x, u: ca.mtimes(ca.DM(A), x) + ca.mtimes(ca.DM(B), u), 2, 1)
    p, w, u = sympy.symbols("p w u")
    sym = System.from_sympy([p + 0.1 * w, 0.2 * p + 0.9 * w + 0.1 * u], [p, w], [u])
    rng = np.random.default_rng(0)
    for _ in range(10):
        x, v = rng.normal(size=2), rng.normal(size=1)
        ref = A @ x + B @ v
        for s in (lin, call, sym):
            np.testing.assert_allclose(s.step(x, v), ref, rtol=1e-14, atol=1e-14)
    J_A, J_B = sym.jacobians(np.zeros(2), np.zeros(1))
    np.testing.assert_allclose(J_A, A)
    np.testing.assert_allclose(J_B, B)


def test_rk4_and_euler_against_the_matrix_exponential():
    Ac = np.array([[0.0, 1.0], [-2.0, -0.3]])
    Bc = np.array([[0.0], [1.0]])
    dt = 0.1
    f = lambda x, u: ca.mtimes(ca.DM(Ac), x) + ca.mtimes(ca.DM(Bc), u)
    rk4 = System.from_continuous(f, 2, 1, dt, method="rk4")
    euler = System.from_continuous(f, 2, 1, dt, method="euler", steps=50)
    M = scipy.linalg.expm(np.block([[Ac, Bc], [np.zeros((1, 3))]]) * dt)
    x, u = np.array([1.0, -0.5]), np.array([0.7])
    exact = M[:2, :2] @ x + M[:2, 2:] @ u
    assert np.max(np.abs(rk4.step(x, u) - exact)) < 1e-6  # O(dt^5) local error
    assert np.max(np.abs(euler.step(x, u) - exact)) < 5e-4  # O(dt^2 / steps)
    with pytest.raises(Exception, match="unknown discretization"):
        System.from_continuous(f, 2, 1, dt, method="leapfrog")


def test_sympy_rejects_unknown_symbols():
    p, q = sympy.symbols("p q")
    with pytest.raises(Exception, match=r"symbols that are not states.*'q'"):
        System.from_sympy([p + q], [p], [])


def test_terminal_cbf_sdp_satisfies_its_lmis(pend):
    h_f = pend.h_f
    A, B = pend.system.A, pend.system.B
    E = h_f.E
    Acl = A + B @ h_f.K
    # invariance with strict decrease: (A+BK)ᵀ P (A+BK) ⪯ λ P
    lam = np.linalg.eigvalsh(h_f.decrease_factor * h_f.P - Acl.T @ h_f.P @ Acl)
    assert lam.min() >= -1e-7
    # the ellipsoid lies in the tightened state constraints and Kx ∈ U on it
    for a, b in zip(pend.X.H, pend.X.h - pend.deltas[-1]):
        assert np.sqrt(a @ E @ a) <= b + 1e-7
    for a, b in zip(pend.U.H, pend.U.h):
        assert np.sqrt(a @ h_f.K @ E @ h_f.K.T @ a) <= b + 1e-7
    # γ_f is the largest level on which Kx ∈ U: tight for some input row
    gamma = h_f.gamma_f
    assert gamma == pytest.approx(largest_level(h_f.P, h_f.K, pend.U))
    scale = np.sqrt(1 + gamma)
    worst = max(np.sqrt(a @ h_f.K @ E @ h_f.K.T @ a) * scale - b
                for a, b in zip(pend.U.H, pend.U.h))
    assert abs(worst) < 1e-9
    # and the SPEC reference: P ≈ [[4.246, 0.212], [0.212, 0.460]] up to the tightening
    assert np.allclose(h_f.P, [[4.246, 0.212], [0.212, 0.460]], atol=0.05)


def test_builder_reads_like_the_math_and_reports_blocks(pend):
    ocp = OCP(pend.system, 5, name="soft_demo")
    x0 = ocp.parameter("x0", 2)
    ocp.initial_state(x0)
    ocp.dynamics()
    ocp.input_constraint(pend.U)
    xi = ocp.state_constraint(pend.X, tightening=lambda i: 1e-3 * i, slack="variable")
    ocp.terminal_constraint(Ellipsoid(pend.h_f.P, name="Xf"))
    ocp.minimize(1e3 * sum_norms(xi, 1) + norm(ocp.u, 2))
    text = ocp.describe()
    for piece in ("var   x", "xi_state", "block dynamics", "block terminal", "norm2"):
        assert piece in text
    assert xi.shape == (4, 5)
    result = compare_backends(ocp, {"x0": [0.3, 0.5]}, targets=("exact", "cvxpy"))
    assert result.agree(rtol=1e-5, atol=1e-6), result.objectives
    for sol in result.solutions.values():
        assert verify(ocp, sol).ok


def test_compile_once_resolve_with_warm_start(pend):
    c = compile(pend.slack, "casadi", "sqpmethod")
    first = c.solve({"x0": [0.9, 0.3]})
    again = c.solve({"x0": [0.9, 0.3]}, warm_start=first)
    assert again.iterations <= 1 and again.objective == pytest.approx(first.objective)
    near = c.solve({"x0": [0.91, 0.3]}, warm_start=first)
    cold = c.solve({"x0": [0.91, 0.3]})
    assert near.objective == pytest.approx(cold.objective, rel=1e-8, abs=1e-8)
    warm_dict = c.solve({"x0": [0.91, 0.3]}, warm_start={"x": first["x"], "u": first["u"]})
    assert warm_dict.objective == pytest.approx(cold.objective, rel=1e-8, abs=1e-8)


def test_hard_constraints_infeasible_is_a_status(pend):
    ocp = OCP(pend.system, 3, name="hard")
    ocp.initial_state(ocp.parameter("x0", 2))
    ocp.dynamics()
    ocp.input_constraint(pend.U)
    ocp.state_constraint(pend.X)
    ocp.minimize(0)
    for backend in ("casadi", "cvxpy"):
        sol = compile(ocp, backend).solve({"x0": [3.0, 0.0]})  # starts outside X
        assert not sol.success and sol.status in ("infeasible", "failed")


def test_terminal_cbf_rejects_bad_data(pend):
    with pytest.raises(Exception, match="origin must lie in the interior"):
        synthesize_terminal_cbf(pend.system.A, pend.system.B, Box([0.1, -1], [1, 1]), pend.U)
    with pytest.raises(Exception, match="decrease factor"):
        synthesize_terminal_cbf(pend.system.A, pend.system.B, pend.X, pend.U,
                                decrease_factor=1.5)
