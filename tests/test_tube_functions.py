"""The CasADi tube functions of Algorithms 5.2/6.4 (:mod:`balustrade.control.tube_functions`)
against the numpy path they replace (:mod:`balustrade.control.robust_steps`): when
:meth:`TubeFunctions.build` falls back to numpy (``None``), the terminal input's closed form
against SLSQP outside ``U ⊖ κ(E)``, and a numpy-only ``π_f`` that is affine only where it was
probed (session 13 review)."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from balustrade.control.robust_steps import robust_candidate
from balustrade.control.tube_functions import TubeFunctions, tube_candidate
from balustrade.dsl.sets import Box
from balustrade.dsl.system import LinearSystem, System

N = 4
A = np.array([[1.0, 0.1], [0.2, 1.05]])
B = np.array([[0.0], [0.1]])
P = np.array([[2.0, 0.3], [0.3, 1.0]])
K = np.array([[-1.0, -2.0]])
X_E = Box([-30.0, -30.0], [30.0, 30.0])
DELTAS = 1e-3 * np.arange(N)
WIDE = Box([-100.0], [100.0])  # U ⊖ κ(E) containing every π_f value below


def h_f(x: object) -> object:
    """``xᵀPx − 1`` on CasADi symbols or numbers."""
    if isinstance(x, (ca.SX, ca.MX, ca.DM)):
        return ca.mtimes([x.T, ca.DM(P), x]) - 1
    x = np.asarray(x, dtype=float).reshape(-1)
    return float(x @ P @ x - 1.0)


def linear_policy(x: np.ndarray) -> np.ndarray:  # numpy only, as the lane change's
    return K @ np.asarray(x, dtype=float).reshape(-1)


def saturating_policy(x: np.ndarray) -> np.ndarray:
    """``clip(Kx, ±10)``: affine at the probes of ``policy_expr`` (|Kx| ≲ 10), not beyond."""
    return np.clip(linear_policy(x), -10.0, 10.0)


def _plan(zN: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    z = np.column_stack([np.full(2, 0.1)] * N + [zN])
    return z, np.zeros((1, N)), np.zeros((X_E.n_rows, N))


def _build(pi_f=linear_policy, U_E=WIDE, system=None, h=h_f, norm=1):
    return TubeFunctions.build(system or LinearSystem(A, B), X_E, U_E, h, pi_f, DELTAS,
                               1e6, norm)


def test_build_falls_back_to_numpy():
    assert isinstance(_build(), TubeFunctions)
    # a numpy-only h_f (fails on symbols)
    assert _build(h=lambda x: float(np.asarray(x, dtype=float) @ P
                                    @ np.asarray(x, dtype=float)) - 1.0) is None
    # a system with parameters θ
    theta_sys = System(lambda x, u, w, th: ca.mtimes(ca.DM(A), x) + ca.mtimes(ca.DM(B), u)
                       * (1 + th), 2, 1, 0, 1, name="theta2")
    assert _build(system=theta_sys) is None
    # a slack norm the tube functions do not support
    assert _build(norm=3) is None


def test_saturating_numpy_policy_is_not_replaced_by_its_affine_probe():
    """At ``z_N`` with |K z_N| = 60 the policy saturates at −10 (inside U ⊖ κ(E)); the
    CasADi candidate's affine map would apply −60: the candidate must be the numpy one."""
    system, U_E = LinearSystem(A, B), Box([-100.0], [100.0])
    tube = _build(pi_f=saturating_policy, U_E=U_E)
    assert isinstance(tube, TubeFunctions)
    z, v, xi = _plan(np.array([20.0, 20.0]))
    assert tube.candidate(z, v, xi) is None
    got = tube_candidate(tube, system, X_E, h_f, saturating_policy, DELTAS, z, v, xi, U_E)
    ref = robust_candidate(system, X_E, h_f, saturating_policy, DELTAS, z, v, xi, U_E)
    assert got.v[0, -1] == -10.0
    np.testing.assert_array_equal(got.z, ref.z)
    # where it is affine the CasADi candidate is used (the lane change's numpy π_f)
    z, v, xi = _plan(np.array([1.0, -2.0]))
    cand = tube.candidate(z, v, xi)
    assert cand is not None
    np.testing.assert_allclose(cand.v[0, -1], 3.0, rtol=1e-12)


def test_terminal_input_outside_u_minus_kappa_e_closed_form_vs_slsqp():
    """``π_f(z_N)`` leaves ``U ⊖ κ(E)``: one input, ``h_f(f(z_N, v))`` quadratic in ``v`` —
    the CasADi candidate's closed-form minimizer over the interval equals SLSQP's (the numpy
    path); with two inputs there is no closed form and the candidate is numpy's."""
    system, U_E = LinearSystem(A, B), Box([-0.5], [0.5])
    tube = _build(U_E=U_E)
    for zN in (np.array([1.0, 1.0]), np.array([-3.0, 0.5]), np.array([0.2, -4.0])):
        z, v, xi = _plan(zN)
        assert not U_E.contains(linear_policy(zN))
        cand = tube.candidate(z, v, xi)
        ref = robust_candidate(system, X_E, h_f, linear_policy, DELTAS, z, v, xi, U_E)
        assert cand is not None
        np.testing.assert_allclose(cand.v, ref.v, atol=1e-6)
        np.testing.assert_allclose(cand.z, ref.z, atol=1e-6)
    B2 = np.array([[0.05, 0.0], [0.1, 0.02]])
    sys2, U2 = LinearSystem(A, B2, name="two_inputs"), Box([-0.5, -0.5], [0.5, 0.5])
    K2 = np.array([[-1.0, -2.0], [0.5, -1.0]])

    def pi2(x):
        return K2 @ np.asarray(x, dtype=float).reshape(-1)

    tube2 = TubeFunctions.build(sys2, X_E, U2, h_f, pi2, DELTAS, 1e6, 1)
    z, _, xi = _plan(np.array([1.0, 1.0]))
    v2 = np.zeros((2, N))
    assert tube2.candidate(z, v2, xi) is None
    got = tube_candidate(tube2, sys2, X_E, h_f, pi2, DELTAS, z, v2, xi, U2)
    ref = robust_candidate(sys2, X_E, h_f, pi2, DELTAS, z, v2, xi, U2)
    np.testing.assert_array_equal(got.v, ref.v)
    assert U2.contains(got.v[:, -1], tol=1e-9)


@pytest.mark.parametrize("pi_f", [linear_policy, saturating_policy])
def test_inside_values_agree_with_numpy(pi_f):
    """Inside the probed region both policies give the numpy candidate to rounding."""
    system, U_E = LinearSystem(A, B), Box([-100.0], [100.0])
    tube = _build(pi_f=pi_f, U_E=U_E)
    z, v, xi = _plan(np.array([0.5, 0.7]))
    cand = tube.candidate(z, v, xi)
    ref = robust_candidate(system, X_E, h_f, pi_f, DELTAS, z, v, xi, U_E)
    np.testing.assert_allclose(cand.z, ref.z, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(cand.xi, ref.xi, rtol=1e-12, atol=1e-14)
