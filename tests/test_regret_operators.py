"""SLP operators of Chapter 3 (SPEC 4 items 13-14): (3.4)-(3.6), (3.12)-(3.15), compression."""

import numpy as np
import pytest

from balustrade.control.regret import RegretController
from balustrade.problems.regret import (
    LTVSystem,
    build_operators,
    controller_from_responses,
    responses_from_controller,
)
from balustrade.problems.regret.operators import noncausal_cost_matrix_alt


def random_ops(seed: int, n: int = 3, m: int = 2, T: int = 5, ltv: bool = True):
    rng = np.random.default_rng(seed)
    k = T if ltv else 1
    A = [0.6 * rng.standard_normal((n, n)) for _ in range(k)]
    B = [rng.standard_normal((n, m)) for _ in range(k)]
    E = [np.eye(n) + 0.2 * rng.standard_normal((n, n)) for _ in range(k)]
    Q = [np.diag(rng.uniform(0.5, 2.0, n)) for _ in range(T + 1)]
    R = [np.diag(rng.uniform(0.5, 2.0, m)) for _ in range(T + 1)]
    if not ltv:
        A, B, E = A[0], B[0], E[0]
    return build_operators(LTVSystem.create(A, B, T, E=E, Q=Q, R=R)), rng


def random_causal_K(ops, rng):
    K = rng.standard_normal((ops.m * (ops.T + 1), ops.n * (ops.T + 1))) * 0.3
    for t, rs in enumerate(ops.u_blocks):
        K[rs, ops.x_blocks[t].stop:] = 0.0
    return K


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_responses_of_a_causal_controller_are_achievable_and_recover_K(seed):
    ops, rng = random_ops(seed)
    K = random_causal_K(ops, rng)
    Phi_x, Phi_u = responses_from_controller(ops, K)
    assert ops.achievability_residual(Phi_x, Phi_u) < 1e-10
    assert ops.is_causal(Phi_u, tol=1e-12) and ops.is_causal(Phi_x, rows="x", tol=1e-12)
    assert np.allclose(ops.phi_x(Phi_u), Phi_x, atol=1e-10)
    assert np.allclose(controller_from_responses(ops, Phi_x, Phi_u), K, atol=1e-9)
    # closed-loop simulation reproduces x = Φ_x δ and u = Φ_u δ
    x0, w = rng.standard_normal(ops.n), rng.standard_normal((ops.T, ops.p))
    run = RegretController(ops, K).simulate(x0, w)
    delta = ops.delta(x0, w)
    assert np.allclose(run.x.reshape(-1), Phi_x @ delta, atol=1e-9)
    assert np.allclose(run.u.reshape(-1), Phi_u @ delta, atol=1e-9)
    assert np.isclose(run.J, delta @ ops.cost_matrix(Phi_x, Phi_u) @ delta, rtol=1e-10)


@pytest.mark.parametrize("seed", [0, 3])
def test_noncausal_benchmark_matches_least_squares_and_both_formulas(seed):
    ops, rng = random_ops(seed, ltv=bool(seed % 2 == 0))
    assert np.allclose(ops.O, noncausal_cost_matrix_alt(ops), rtol=1e-9, atol=1e-9)
    delta = rng.standard_normal(ops.nd)
    # J* by an independent least-squares solve over all inputs u (3.4)
    Qh = np.linalg.cholesky(ops.Qcal + 1e-300 * np.eye(ops.Qcal.shape[0]))
    Rh = np.linalg.cholesky(ops.Rcal)
    A_ls = np.vstack([Qh.T @ ops.F, Rh.T])
    b_ls = -np.concatenate([Qh.T @ ops.G @ delta, np.zeros(ops.Rcal.shape[0])])
    u_star = np.linalg.lstsq(A_ls, b_ls, rcond=None)[0]
    x_star = ops.F @ u_star + ops.G @ delta
    assert np.isclose(ops.cost(x_star, u_star), ops.noncausal_cost(delta), rtol=1e-9)
    assert np.allclose(u_star, ops.Phi_u_nc @ delta, atol=1e-8)


@pytest.mark.parametrize("seed", [0, 1])
def test_regret_is_a_sum_of_squares_for_every_achievable_phi(seed):
    ops, rng = random_ops(seed)
    Phi_x, Phi_u = responses_from_controller(ops, random_causal_K(ops, rng))
    M = ops.cost_matrix(Phi_x, Phi_u) - ops.O
    Y = ops.regret_factor(Phi_u)
    assert np.allclose(M, Y.T @ Y, atol=1e-8 * max(1.0, np.abs(M).max()))
    assert np.min(np.linalg.eigvalsh(0.5 * (M + M.T))) > -1e-8 * np.abs(M).max()
    # S is lower triangular and squares to the input Hessian
    assert np.allclose(np.triu(ops.S, 1), 0.0)
    assert np.allclose(ops.S.T @ ops.S, ops.H, atol=1e-9)


def test_regret_controller_steps_like_every_controller():
    """``step(x, u_p) -> (u, StepInfo)`` with its own history gives the inputs of the rollout;
    ``reset`` restarts at k = 0; past the horizon it applies 0 and says so; the rollout's
    trace is the common :class:`Trace`."""
    from balustrade.control.base import StepInfo, Trace

    ops, rng = random_ops(4)
    ctrl = RegretController(ops, random_causal_K(ops, rng))
    x0, w = rng.standard_normal(ops.n), rng.standard_normal((ops.T, ops.p))
    run = ctrl.simulate(x0, w)
    assert isinstance(run.trace, Trace) and run.trace.n_fallbacks == 0
    assert run.x.shape == (ops.T + 1, ops.n) and run.u.shape == (ops.T + 1, ops.m)
    ctrl.reset()
    for k in range(ops.T + 1):
        u, info = ctrl.step(run.x[k], np.zeros(ops.m))
        assert isinstance(info, StepInfo) and info.status == "ok"
        assert np.allclose(u, run.u[k], atol=1e-14)
    u, info = ctrl.step(run.x[-1], np.zeros(ops.m))
    assert info.fallback == "zero_input" and not u.any()
    ctrl.reset()
    assert np.allclose(ctrl.step(x0, np.zeros(ops.m))[0], run.u[0], atol=1e-14)
