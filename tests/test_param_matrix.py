"""Constraint matrices affine in the parameters on the convex backends (issue #15 item 1):
rows ``A(p) w + B p + c`` with ``A(p) = A₀ + Σ_k p_k A_k`` are classified once
(:class:`~balustrade.backends.passes.classify.Bilinear`), the direct backend updates the values
of ``A(p)`` on a fixed pattern per solve and cvxpy keeps the DPP product — so a new ``p``
never recompiles and gives the answer of a fresh compile with the numbers substituted; and
Algorithm 4.1 (:class:`~balustrade.control.rapsf.RAPSF`) compiles (4.5) once on every target.
"""

from __future__ import annotations

from types import SimpleNamespace

import casadi as ca
import numpy as np
import pytest

import balustrade.control.rapsf as rapsf_module
from balustrade.backends import compile
from balustrade.backends.passes.classify import Affine, Classify
from balustrade.control.rapsf import RAPSF
from balustrade.dsl.costs import norm, squared_norm
from balustrade.dsl.ocp import OCP
from balustrade.dsl.sets import Box
from balustrade.errors import BalustradeError, ConvexityError
from balustrade.estimate import BoxUpdate
from balustrade.problems.rapsf import model_matrices

TARGETS = ("exact", "cvxpy", "fast-convex", "fast-convex-conic")
#: parameter values: feasible ones, one where x1 enters row 0 only through p (a1 = 0 → ≠ 0)
PS = [np.array([0.0, 0.0]), np.array([0.5, -0.3]), np.array([-0.4, 0.8]),
      np.array([1.2, 0.1])]


def _problem(a: object, cost: str = "squared") -> OCP:
    """``min cost(x − (2, ½, 0))`` s.t. ``(1 + a₀) x₀ + a₁ x₁ <= 1 + ½ a₁``,
    ``x₀ + a₀ x₁ − x₂ == 0.2 + 0.1 a₁``, ``|x| <= 1`` — with ``a`` a parameter (rows affine in
    ``x`` with coefficients affine in ``a``; the coefficient of ``x₁`` in row 0 is zero at
    ``a = 0``, so ``A(a)`` needs the union pattern) or numbers (the constant problem)."""
    ocp = OCP(name=f"param_matrix_{cost}")
    x = ocp.variable("x", 3, lb=-1.0, ub=1.0)
    if a is None:
        a = ocp.parameter("a", 2)
    else:
        a = ca.DM(np.asarray(a, dtype=float))
    ocp.le((1 + a[0]) * x[0] + a[1] * x[1], 1 + 0.5 * a[1], name="tilted")
    ocp.eq(x[0] + a[0] * x[1] - x[2], 0.2 + 0.1 * a[1], name="coupling")
    target = ca.DM([2.0, 0.5, 0.0])
    ocp.minimize(squared_norm(x - target) if cost == "squared" else norm(x - target, 2))
    return ocp


def _agree(compiled, p: np.ndarray, cost: str, tol: float = 1e-8) -> bool:
    """The parametric ``compiled`` at ``p`` equals a fresh compile of the constant problem
    (objective to ``tol``; the point to ``100 tol``, ``1000 tol`` for the 2-norm cost, whose
    minimizer is determined only to about the square root of the solver's gap)."""
    sol = compiled.solve({"a": p})
    ref = compile(_problem(p, cost), compiled.target).solve()
    assert ref.status == "optimal", ref.summary()
    xtol = (1000 if cost == "norm2" else 100) * tol
    return sol.status == "optimal" and abs(sol.objective - ref.objective) <= tol * max(
        1.0, abs(ref.objective)) and bool(np.allclose(sol["x"], ref["x"], atol=xtol))


def test_classify_records_the_parameter_structure():
    """``A(p) = A₀ + Σ p_k A_k`` of the classified rows equals CasADi's Jacobian at random
    ``p``; the offset ``B p + c`` is the row's value at ``w = 0``."""
    ocp = _problem(None)
    cls, _ = Classify().apply(ocp)
    w, p = ocp.decision_vector(), ocp.parameter_vector()
    rng = np.random.default_rng(0)
    for cb in cls.blocks:
        (piece,) = cb.pieces
        aff = piece.form
        assert isinstance(aff, Affine) and aff.Ap is not None, cb.block.name
        J = ca.Function("J", [w, p], [ca.jacobian(cb.block.expr, w), cb.block.expr])
        for _ in range(3):
            pv, wv = rng.normal(size=2), rng.normal(size=3)
            Jv, value = (np.asarray(v, float) for v in J(wv, pv))
            A = aff.A.toarray() + aff.Ap.matrix(pv, 3).toarray()
            assert np.allclose(A, Jv, atol=1e-14)
            assert np.allclose(A @ wv + aff.B @ pv + aff.c, value.ravel(), atol=1e-13)


@pytest.mark.parametrize("cost", ["squared", "norm2"])
def test_backends_agree_with_parameters_times_variables(cost):
    ocp = _problem(None, cost)
    compiled = {t: compile(ocp, t) for t in TARGETS}
    for p in PS:
        sols = {t: c.solve({"a": p}) for t, c in compiled.items()}
        assert all(s.status == "optimal" for s in sols.values()), \
            {t: s.summary() for t, s in sols.items()}
        x = np.array([s["x"] for s in sols.values()])
        obj = np.array([s.objective for s in sols.values()])
        assert np.ptp(x, axis=0).max() < 1e-5, (p, x)
        assert np.ptp(obj) < 1e-6 * max(1.0, abs(obj[0])), (p, obj)


@pytest.mark.parametrize("target", ["cvxpy", "fast-convex", "fast-convex-conic"])
@pytest.mark.parametrize("cost", ["squared", "norm2"])
def test_new_parameters_without_recompiling_equal_a_fresh_constant_compile(target, cost):
    if target == "fast-convex" and cost == "norm2":
        target = "fast-convex-conic"  # a cone: PIQP cannot take it
    compiled = compile(_problem(None, cost), target)
    for p in PS + PS[::-1]:                 # back and forth: no state carried between solves
        assert _agree(compiled, p, cost), (target, p)


def test_negative_control_skipping_the_matrix_update_gives_wrong_answers():
    """If the values of ``A(p)`` were not updated (the solver kept ``A(0)``), the direct
    backend would solve another problem: the comparison with a fresh compile fails."""
    compiled = compile(_problem(None), "fast-convex")
    assert compiled.program.A_param is not None
    compiled.program.A_param = None                   # "A does not depend on p"
    assert _agree(compiled, PS[0], "squared")          # at p = 0 nothing changes
    assert not any(_agree(compiled, p, "squared") for p in PS[1:])


@pytest.mark.parametrize("target", ["fast-convex", "fast-convex-conic", "cvxpy"])
def test_infeasible_parameters_are_reported_and_the_next_solve_is_right(target):
    """``a₁ = 8``: ``x₀ + a₀x₁ − x₂ = 1`` and ``(1 + a₀)x₀ + 8x₁ <= 5`` stay feasible, but
    ``a = (0, 30)`` asks ``x₀ − x₂ = 3.2`` with ``|x| <= 1``: infeasible (confirmed by the
    feasibility solve, which gets the same ``A(p)``); the next solve is right again."""
    compiled = compile(_problem(None), target)
    bad = compiled.solve({"a": np.array([0.0, 30.0])})
    assert bad.status == "infeasible", bad.summary()
    assert np.all(np.isnan(bad["x"]))
    assert _agree(compiled, PS[1], "squared")


@pytest.mark.parametrize("target", ["fast-convex", "fast-convex-conic", "cvxpy"])
def test_the_infeasibility_check_sees_the_same_matrix(target):
    """``(1 − a) x₀ = ½`` is feasible at ``a = 0`` and infeasible at ``a = 1``: the feasibility
    solve that confirms "infeasible" must get ``A(p)`` too — with ``A(0)`` it would find the
    constraints feasible and report ``failed``."""
    ocp = OCP(name="vanishing_row")
    x = ocp.variable("x", 2, lb=-1.0, ub=1.0)
    a = ocp.parameter("a", 1)
    ocp.eq((1 - a[0]) * x[0], 0.5, name="vanishing")
    ocp.minimize(squared_norm(x - 0.2))
    compiled = compile(ocp, target)
    assert compiled.solve({"a": 1.0}).status == "infeasible"
    ok = compiled.solve({"a": 0.5})
    assert ok.status == "optimal" and ok["x"][0] == pytest.approx(1.0, abs=1e-7)


def test_parameter_times_variable_elsewhere_is_still_refused():
    """Only affine rows take ``p · w``: inside a quadratic row the direct backend refuses it
    naming the block."""
    ocp = OCP(name="quadratic_row")
    x = ocp.variable("x", 2, lb=-1.0, ub=1.0)
    a = ocp.parameter("a", 1)
    ocp.le(x[0] ** 2 + a[0] * x[1], 0.5, name="bowl")
    ocp.minimize(squared_norm(x - 1.0))
    with pytest.raises(ConvexityError, match="bowl"):
        compile(ocp, "fast-convex")


# -- Algorithm 4.1: (4.5) with the Θ_k-vertex data as parameters --------------------------------
N = 8


@pytest.fixture(scope="module")
def toy(rapsf_toy) -> SimpleNamespace:
    return rapsf_toy             # tests/conftest.py


def _closed_loop(t, target, vertex_data, steps=12, monkeypatch=None):
    """Algorithm 4.1 with the box update; ``(u, objective, compiles)`` per step."""
    calls = []
    if monkeypatch is not None:
        def counting(ocp, tgt):
            calls.append(ocp.name)
            return compile(ocp, tgt)
        monkeypatch.setattr(rapsf_module, "compile", counting)
    ctrl = RAPSF(t.sys, t.X0, t.F, t.G, t.W, t.K, N, t.Theta0,
                 estimator=BoxUpdate(t.sys, t.W, t.Theta0), target=target,
                 vertex_data=vertex_data)
    A, B = model_matrices(t.sys, np.array([0.9, 0.2]))
    rng = np.random.default_rng(3)
    x, us, objs, thetas = np.array([0.9, 0.2]), [], [], []
    for k in range(steps):
        u, info = ctrl.step(x, np.array([3.0 * np.sin(0.4 * k) + 1.5]))
        assert info.fallback is None and info.status == "ok", (k, info.status)
        us.append(u.copy())
        objs.append(info.values["objective"])
        thetas.append(ctrl.Theta.vertices().copy())
        x = A @ x + B @ u + 0.004 * rng.uniform(-1, 1, 2)
    return np.array(us), np.array(objs), thetas, calls


@pytest.mark.parametrize("target", ["fast-convex", "cvxpy"])
def test_rapsf_compiles_once_over_a_closed_loop(toy, target, monkeypatch):
    us, objs, thetas, calls = _closed_loop(toy, target, "parameters", monkeypatch=monkeypatch)
    assert len({th.tobytes() for th in thetas}) > 3      # Θ_k changed several times ...
    assert calls == [f"rapsf_N{N}"]                     # ... and (4.5) was compiled once


@pytest.mark.parametrize("target", ["exact", "cvxpy", "fast-convex", "fast-convex-conic"])
def test_rapsf_parametric_and_constant_vertex_data_agree(toy, target, monkeypatch):
    us_c, objs_c, th_c, calls = _closed_loop(toy, target, "constants", steps=8,
                                             monkeypatch=monkeypatch)
    assert len(calls) > 1                               # the constant form recompiles
    us_p, objs_p, th_p, _ = _closed_loop(toy, target, "parameters", steps=8)
    assert np.allclose(us_p, us_c, atol=1e-6, rtol=1e-6), (us_p - us_c).ravel()
    assert np.allclose(objs_p, objs_c, atol=1e-6, rtol=1e-6)
    assert all(np.allclose(a, b) for a, b in zip(th_p, th_c, strict=True))


def test_rapsf_vertex_data_option_is_checked(toy):
    with pytest.raises(BalustradeError, match="vertex_data"):
        RAPSF(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, toy.Theta0,
              vertex_data="numbers")


@pytest.mark.parametrize("target", ["fast-convex", "cvxpy"])
def test_rapsf_pads_fewer_vertices_without_recompiling(toy, target):
    """A Θ_k with fewer vertices than compiled (a point: 1 of 4) repeats them: same compiled
    problem, and the answer of the constant form with that single vertex."""
    ctrl = RAPSF(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, toy.Theta0, target=target)
    const = RAPSF(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, toy.Theta0, target=target,
                  vertex_data="constants")
    x, u_p = np.array([0.5, 0.1]), np.array([1.0])
    ctrl.step(x, u_p)
    point = Box([0.9, 0.2], [0.9, 0.2])
    ctrl._set_theta(point)
    const._set_theta(point)
    u, info = ctrl.step(x, np.array([10.0]))
    uc, infoc = const.step(x, np.array([10.0]))
    assert info.status == "ok" and infoc.status == "ok"
    assert info.values["objective"] > 1e-3                     # the filter is active
    assert list(ctrl._compiled) == [(N, 4)]
    assert np.allclose(u, uc, atol=1e-6)
    assert info.values["objective"] == pytest.approx(infoc.values["objective"], abs=1e-7)
