"""The epigraph pass: apply/invert round trip and exact values for ‖·‖₁, ‖·‖₂, ‖·‖∞, max."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from balustrade.backends.passes import CASADI_CHAIN, Epigraph, invert_chain, run_chain
from balustrade.backends.passes.epigraph import NORM2_EPS, SmoothProblem
from balustrade.dsl import OCP, max_of, norm, quad

# t as a function of a at the tight point of each epigraph form (t is a vector for ‖·‖₁)
TIGHT = {"norm1": np.abs, "norm2": lambda a: np.array([np.linalg.norm(a)]),
         "norminf": lambda a: np.array([np.abs(a).max()]), "max": lambda a: np.array([a.max()])}
COSTS = {"norm1": lambda a: norm(a, 1), "norm2": lambda a: norm(a, 2),
         "norminf": lambda a: norm(a, np.inf), "max": max_of}


def _ocp(kind: str, lb: float = -np.inf) -> tuple[OCP, ca.SX]:
    ocp = OCP(name=f"epi_{kind}")
    a = ocp.variable("a", 3, lb=lb)
    p = ocp.parameter("p", 3)
    ocp.minimize(2.0 * COSTS[kind](a - p) + quad(a))
    return ocp, a


def _functions(sp: SmoothProblem) -> tuple[ca.Function, ca.Function]:
    return ca.Function("f", [sp.w, sp.p], [sp.f]), ca.Function("g", [sp.w, sp.p], [sp.g])


@pytest.mark.parametrize("kind", sorted(TIGHT))
def test_epigraph_value_equals_declared_cost(kind):
    ocp, _ = _ocp(kind)
    sp, inverse = Epigraph().apply(ocp)
    added = sp.variables.added
    assert [e.origin for e in added] == ["epigraph"]
    assert added[0].size == (3 if kind == "norm1" else 1)
    lb, _ = sp.variables.bounds()
    assert np.all(lb[3:] == (-np.inf if kind == "max" else 0.0))
    f, g = _functions(sp)
    rng = np.random.default_rng(1)
    for _ in range(20):
        a, p = rng.normal(size=3), rng.normal(size=3)
        t = TIGHT[kind](a - p)
        w_all = np.concatenate([a, t])
        rows = np.asarray(g(w_all, p)).reshape(-1)
        assert np.all(rows <= 1e-12)  # the tight t is feasible ...
        declared = float(ca.Function("c", [sp.w, sp.p], [sp.cost])(w_all, p))
        assert float(f(w_all, p)) == pytest.approx(declared, rel=1e-12, abs=1e-12)
        shrunk = np.concatenate([a, t - 1e-6])  # ... and no smaller t is
        assert np.asarray(g(shrunk, p)).max() > 0
        # invert: the user's variables only, objective the declared cost
        primal, objective = Epigraph().invert((w_all, p), inverse)
        assert list(primal) == ["a"]
        np.testing.assert_array_equal(primal["a"], a)
        assert objective == pytest.approx(declared, rel=1e-14)


def test_norm2_rows_near_the_apex_use_max_t_eps():
    ocp, _ = _ocp("norm2")
    sp, _ = Epigraph().apply(ocp)
    _, g = _functions(sp)
    a = np.array([3e-7, 0.0, 0.0])  # aᵀa / max(t, ε) − t at t = 0 divides by ε, not by 0
    rows = np.asarray(g(np.r_[a, 0.0], np.zeros(3))).reshape(-1)
    assert rows[0] == pytest.approx(9e-14 / NORM2_EPS)


def test_nonnegative_norm1_has_no_epigraph_variable():
    ocp, a = _ocp("norm1", lb=0.0)
    ocp.minimize(norm(a, 1))
    sp, inverse = Epigraph().apply(ocp)
    assert not sp.variables.added and sp.g.numel() == 0
    f = ca.Function("f", [sp.w, sp.p], [sp.f])
    assert float(f([1, 2, 3], np.zeros(3))) == 6.0
    ocp.minimize(norm(a, np.inf))  # ‖ξ‖∞ of nonnegative ξ: a_j <= t only
    sp, _ = Epigraph().apply(ocp)
    assert sp.g.numel() == 3


def test_rows_follow_the_users_blocks_and_chain_inverts():
    ocp, a = _ocp("norm2")
    ocp.le(a, 1.0, name="box")
    ocp.eq(ca.sum1(a), 0.0, name="sum")
    data, inverses = run_chain(CASADI_CHAIN, ocp)
    assert data.block_rows == {"box": slice(0, 3), "sum": slice(3, 4)}
    assert data.n_g_user == 4 and data.lbg.size == 4 + 1 + 3 + 3  # cone, a−t, −a−t
    assert data.layout.user_size == 3 and data.layout.size == 4
    np.testing.assert_array_equal(data.x0, np.zeros(4))
    w_all, p = np.array([0.1, -0.2, 0.1, 0.3]), np.ones(3)
    primal, objective = invert_chain(inverses, (w_all, p))
    np.testing.assert_array_equal(primal["a"], w_all[:3])
    assert objective == pytest.approx(2 * np.linalg.norm(w_all[:3] - 1) + w_all[:3] @ w_all[:3])


def test_chain_refuses_what_a_pass_does_not_accept():
    from balustrade.backends.passes import CVXPY_CHAIN
    from balustrade.errors import BalustradeError

    ocp, _ = _ocp("max")
    smooth, _ = Epigraph().apply(ocp)
    with pytest.raises(BalustradeError, match="pass 'classify' cannot take SmoothProblem"):
        run_chain(CVXPY_CHAIN, smooth)
    with pytest.raises(BalustradeError, match="pass 'epigraph' cannot take SmoothProblem"):
        run_chain(CASADI_CHAIN, smooth)
