"""Bad input raises balustrade errors naming the argument; infeasible synthesis returns a status."""

import numpy as np
import pytest

from balustrade.backends import resolve_target
from balustrade.control.regret_synthesis import (
    dynamic_regret,
    generalized_regret,
    pointwise_regret,
    zero_x0_regret,
)
from balustrade.errors import BalustradeError, NotPSDError, ShapeError
from balustrade.problems.regret import LTVSystem, StateInputConstraints, build_operators
from balustrade.problems.regret.verify import maximize_quadratic_on_ball

A = np.array([[1.0, 0.1], [0.0, 1.0]])
B = np.array([[0.0], [0.1]])


def test_non_psd_weights_are_named():
    with pytest.raises(NotPSDError, match=r"Q\[0\]"):
        LTVSystem.create(A, B, 3, Q=np.diag([1.0, -1.0]))
    with pytest.raises(NotPSDError, match=r"R\[2\]"):
        LTVSystem.create(A, B, 3, R=[np.eye(1), np.eye(1), np.zeros((1, 1)), np.eye(1)])
    ops = build_operators(LTVSystem.create(A, B, 3))
    with pytest.raises(NotPSDError, match="P"):
        pointwise_regret(ops, [1.0, 0.0], -np.eye(2))
    with pytest.raises(NotPSDError, match="W"):
        generalized_regret(ops, [1.0, 0.0], 1.0, W=-np.eye(ops.nd))


def test_competitive_ratio_needs_a_nonsingular_benchmark():
    """W = "O" needs 𝒪 ≻ 0 ((3.11) asks W_w ≻ 0). With Q_k = diag(1, 0) the state x₂ costs
    nothing, 𝒪 is singular (its smallest eigenvalue is 0, computed here independently of the
    check) and (3.30) crashed in its certificate with numpy's LinAlgError after the solve."""
    ops = build_operators(LTVSystem.create(A, B, 3, Q=np.diag([1.0, 0.0])))
    assert np.linalg.eigvalsh(ops.O)[0] < 1e-9 * np.abs(ops.O).max()
    for synth in (lambda: zero_x0_regret(ops, W="O"),
                  lambda: generalized_regret(ops, [1.0, 0.0], 1.0, W="O"),
                  lambda: pointwise_regret(ops, [1.0, 0.0], np.eye(2), W="O")):
        with pytest.raises(NotPSDError, match="W='O'.*positive definite"):
            synth()
    ok = build_operators(LTVSystem.create(A, B, 3))   # Q_k = I: 𝒪 ≻ 0, accepted
    assert zero_x0_regret(ok, W="O").ok


def test_disturbance_matrix_without_full_row_rank():
    with pytest.raises(BalustradeError, match=r"E\[1\].*full row rank"):
        LTVSystem.create(A, B, 3, E=[np.eye(2), np.array([[1.0, 1.0], [1.0, 1.0]]), np.eye(2)])
    with pytest.raises(BalustradeError, match=r"E\[0\]"):
        LTVSystem.create(A, B, 3, E=np.array([[1.0], [0.0]]))


def test_wrong_horizon_lengths_and_shapes():
    with pytest.raises(ShapeError, match="A.*T=4.*3 matrices"):
        LTVSystem.create([A, A, A], B, 4)
    with pytest.raises(ShapeError, match="Q"):
        LTVSystem.create(A, B, 3, Q=[np.eye(2)] * 3)          # needs T + 1 = 4
    with pytest.raises(ShapeError, match="B"):
        LTVSystem.create(A, np.ones((3, 1)), 3)
    ops = build_operators(LTVSystem.create(A, B, 3))
    with pytest.raises(ShapeError, match="x0"):
        dynamic_regret(ops, [1.0, 0.0, 0.0], 1.0)
    with pytest.raises(BalustradeError, match="omega"):
        dynamic_regret(ops, [1.0, 0.0], -1.0)
    with pytest.raises(BalustradeError, match="T"):
        LTVSystem.create(A, B, 0)
    with pytest.raises(BalustradeError, match="b_i > 0"):
        StateInputConstraints.from_halfspaces(np.eye(2), [1.0, 0.0], np.eye(1), [1.0])


def test_infeasible_synthesis_returns_a_status():
    ops = build_operators(LTVSystem.create(A, B, 4))
    # |x_i| ≤ 0.01 cannot be kept robustly against ‖w_k‖ ≤ 1: the first step already fails
    tight = StateInputConstraints.from_halfspaces(np.vstack([np.eye(2), -np.eye(2)]),
                                                  np.full(4, 0.01), np.array([[1.0], [-1.0]]),
                                                  np.full(2, 1.0))
    res = pointwise_regret(ops, [0.0, 0.0], np.eye(2), constraints=tight)
    assert not res.ok and "infeasible" in res.status
    assert res.K is None and res.level is None
    with pytest.raises(BalustradeError, match="no controller"):
        res.controller()


def test_trust_region_hard_and_easy_cases():
    rng = np.random.default_rng(0)
    Amat = np.diag([3.0, 1.0, 0.5])
    # hard case: b orthogonal to the top eigenvector and small
    hard = maximize_quadratic_on_ball(Amat, np.array([0.0, 0.1, 0.0]), 0.0, 4.0)
    assert hard.hard_case and hard.value == pytest.approx(hard.upper, rel=1e-12)
    easy = maximize_quadratic_on_ball(Amat, np.array([1.0, 0.2, 0.0]), 1.0, 4.0)
    assert not easy.hard_case and easy.value == pytest.approx(easy.upper, rel=1e-10)
    for res, b in ((hard, [0.0, 0.1, 0.0]), (easy, [1.0, 0.2, 0.0])):
        assert res.w @ res.w == pytest.approx(4.0, rel=1e-9)
        c = 1.0 if res is easy else 0.0
        for _ in range(200):                   # no sampled point beats the certificate
            v = rng.standard_normal(3)
            v *= 2.0 / np.linalg.norm(v) * rng.uniform(0, 1) ** (1 / 3)
            assert v @ Amat @ v + 2 * np.dot(b, v) + c <= res.value + 1e-12


def test_dense_cone_too_large_for_clarabel_is_a_status(monkeypatch):
    """SCRW (W = 𝒪 with pointwise bounds) outside banded coordinates is one dense cone; when
    Clarabel's KKT block would not fit in memory the synthesis returns the common status
    "failed" with a message naming the size and SCS. In banded coordinates (the default) it is
    decomposable and solved."""
    import balustrade.backends.synthesis_cvxpy as syn

    ops = build_operators(LTVSystem.create(A, B, 3))
    monkeypatch.setattr(syn, "_mem_available_bytes", lambda: 1e3)
    res = pointwise_regret(ops, [1.0, 0.0], np.eye(2), "O", lmi="split")
    assert res.status == "failed" and not res.ok and res.message.startswith("too large")
    assert "size 11" in res.message and "scs" in res.message
    with pytest.raises(BalustradeError, match="failed.*too large"):
        res.controller()
    scs = resolve_target("cvxpy", solver="scs", options={"eps_abs": 1e-7, "eps_rel": 1e-7})
    res_scs = pointwise_regret(ops, [1.0, 0.0], np.eye(2), "O", target=scs, lmi="split")
    res_banded = pointwise_regret(ops, [1.0, 0.0], np.eye(2), "O")
    assert res_banded.ok and res_banded.info["lmi"] == "banded"
    monkeypatch.undo()
    # the same dense cone once it fits: Clarabel's split solve against SCS's and the banded one
    res_cl = pointwise_regret(ops, [1.0, 0.0], np.eye(2), "O", lmi="split")
    assert res_cl.info["lmi"] == "split"
    assert res_scs.ok and res_cl.ok
    assert res_scs.level == pytest.approx(res_cl.level, rel=1e-4)
    assert res_banded.level == pytest.approx(res_cl.level, rel=1e-6)


@pytest.mark.parametrize("eps", [1e-6, 1e-8, 1e-10])
def test_trust_region_near_hard_case_attains_its_dual_bound(eps):
    """β tiny but nonzero on the top eigenvector: ν − α_max is below the resolution of the
    secular equation. The attained value must still meet the dual bound (before the fix the
    maximizer stopped short of the boundary and the gap was ~1e-6 relative on the rocket)."""
    Amat = np.diag([3.0, 1.0, 0.5, -2.0])
    b = np.array([eps, 0.3, -0.2, 0.1])
    res = maximize_quadratic_on_ball(Amat, b, 0.5, 2.0)
    assert res.w @ res.w == pytest.approx(2.0, rel=1e-12)
    assert res.value == pytest.approx(res.upper, rel=1e-10, abs=1e-12)


def test_trust_region_interior_maximum_of_a_concave_quadratic():
    """max 1 − ‖w‖² over ‖w‖² ≤ 2 is 1 at w = 0 (ν = 0): the solver used to force the boundary
    (ν = α_max = −1) and report −1 as both the attained value and the 'upper' bound."""
    r = maximize_quadratic_on_ball(-np.eye(2), np.zeros(2), 1.0, 2.0)
    assert r.value == pytest.approx(1.0, abs=1e-12) and r.upper >= r.value - 1e-12
    # b ≠ 0, interior: −A⁻¹b = (0.25, −0.1) lies in the ball; max = c + bᵀ(−A)⁻¹b
    A2, b2 = -np.diag([2.0, 5.0]), np.array([0.5, -0.5])
    r = maximize_quadratic_on_ball(A2, b2, 0.3, 1.0)
    assert r.value == pytest.approx(0.3 + 0.25 / 2 + 0.25 / 5, rel=1e-12)
    assert r.w == pytest.approx([0.25, -0.1])


def test_generalized_level_of_a_controller_with_an_interior_worst_case():
    """generalized_level_energy (the 'exact' certificate that becomes the reported level of
    (3.28)) for a controller bad for x₀ and open loop for w, ω = 100: at the level the inner
    maximum is interior (M_ww − μI ≺ 0). The old level 7.85 was beaten by the explicit
    disturbance w = (μI − M_ww)⁻¹M_wx x₀ (‖w‖² = 6.9 ≤ ω, regret − μδᵀδ = +292); the level must
    leave that point (and its own interior stationary point) at ≤ 0."""
    from balustrade.problems.regret.verify import generalized_level_energy, regret_matrix

    ops = build_operators(LTVSystem.create(np.array([[0.5, 0.2], [0.0, 0.6]]),
                                           np.array([[0.0], [1.0]]), 4))
    n, om, x0 = ops.n, 100.0, np.array([5.0, -3.0])
    Pu = np.zeros((ops.m * (ops.T + 1), ops.nd))
    Pu[:, :n] = 3.0 * np.random.default_rng(0).standard_normal((Pu.shape[0], n))
    M = regret_matrix(ops, Pu)
    mu = generalized_level_energy(ops, Pu, x0, om, np.eye(ops.nd))
    for level in (7.852401180192828, mu):
        A_ww = M[n:, n:] - level * np.eye(ops.nd - n)
        if np.linalg.eigvalsh(A_ww).max() >= 0:
            continue
        w = np.linalg.solve(-A_ww, M[n:, :n] @ x0)
        d = np.concatenate([x0, w])
        excess = float(d @ (M - level * np.eye(ops.nd)) @ d)
        if level == mu:
            assert w @ w <= om and excess <= 1e-7 * mu
        else:
            assert w @ w <= om and excess > 100.0   # the old level is beaten
    assert mu > 15.0
