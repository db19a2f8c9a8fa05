"""Joint state–input constraints ``𝒵 = {Fx + Gu <= 1}`` as a language element (issue #15 §1,
SPEC §2.20): the set :class:`balustrade.dsl.JointPolytope` and the block
:func:`balustrade.dsl.joint_constraint`, used by the RAPSF QP (4.5) and the baseline PSF.

The stored optima below were computed with the hand-written (4.5d) rows that this block
replaced (commit b93a033, same toy, same data): the QP is unchanged."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from balustrade.backends import compile
from balustrade.dsl import OCP, Box, JointPolytope, LinearSystem, joint_constraint, squared_norm
from balustrade.dsl.joint import as_joint
from balustrade.dsl.sets import Ellipsoid, Polytope
from balustrade.errors import BalustradeError, NonFiniteError, ShapeError
from balustrade.problems.baseline_psf import baseline_psf_problem
from balustrade.problems.rapsf import joint_constraints, rapsf_problem, tube_constants

N = 8
TARGETS = ("exact", "cvxpy", "fast-convex")
# (x0, u_p) -> (optimal value, v*_0) of (4.5) on the toy with the vertices of Θ₀ as constants
RAPSF_REF = [((1.5, 1.0), 3.0, 23.197788366082126, 15.728383802908112),
             ((-0.3, 0.4), -5.0, 4.000000000000252, -0.30973193880273997)]
# the baseline PSF with W̃ = [−0.01, 0.01]²
BASELINE_REF = [((1.5, 1.0), 8.0, 25.00000000000025, 20.544792046203305),
                ((-1.0, 0.5), -6.0, 9.000000000000254, -2.6424765605063327)]


@pytest.fixture(scope="module")
def toy(rapsf_toy):
    return rapsf_toy             # tests/conftest.py


def _Z(toy) -> JointPolytope:
    return JointPolytope(toy.F, toy.G, name="Z")


# -- (4.5) and the baseline: same optimum as before, on every backend ----------------------
@pytest.mark.parametrize("spelling", ["matrices", "set"])
def test_rapsf_qp_optimum_unchanged(toy, spelling: str) -> None:
    """(4.5) with 𝒵 given as ``(F, G)`` or as a ``JointPolytope``: the stored optimum and
    ``v*_0`` of the hand-written rows, on CasADi, cvxpy and the direct backend."""
    FG = (toy.F, toy.G) if spelling == "matrices" else (_Z(toy), None)
    ocp = rapsf_problem(toy.sys, toy.X0, *FG, toy.W, toy.K, N, vertices=toy.V)
    block = next(b for b in ocp.blocks if b.name == "tube_constraints")
    assert block.rows == N * toy.F.shape[0] and block.info["set"]
    for x, u_p, f_ref, v_ref in RAPSF_REF:
        for tg in TARGETS:
            sol = compile(ocp, tg).solve({"x0": np.array(x), "u_p": np.array([u_p])})
            assert sol.status == "optimal", tg
            assert abs(sol.objective - f_ref) <= 1e-6 * max(1.0, f_ref), (tg, sol.objective)
            assert abs(sol["v"][0, 0] - v_ref) <= 1e-5, (tg, sol["v"][0, 0])


def test_rapsf_parametric_vertices_take_the_set(toy) -> None:
    """The parametric form (vertex data as parameters) with 𝒵 as a set gives the same
    optimum, and ``tube_constants`` accepts the set too (same ``t``)."""
    from balustrade.problems.rapsf import s_constants

    ocp = rapsf_problem(toy.sys, toy.X0, _Z(toy), None, toy.W, toy.K, N)
    s = s_constants(toy.X0, toy.sys, toy.K, toy.V)
    (x, u_p, f_ref, _) = RAPSF_REF[0]
    sol = compile(ocp, "exact").solve({"x0": np.array(x), "u_p": np.array([u_p]),
                                       "theta": toy.V.T, "s": s})
    assert sol.status == "optimal" and abs(sol.objective - f_ref) <= 1e-6 * f_ref
    a = tube_constants(toy.X0, toy.W, toy.sys, toy.K, toy.V, toy.F, toy.G)
    b = tube_constants(toy.X0, toy.W, toy.sys, toy.K, toy.V, _Z(toy), None)
    np.testing.assert_array_equal(a.t, b.t)


def test_baseline_psf_optimum_unchanged(toy) -> None:
    W_tilde = Box.symmetric(0.01, 2, name="W_tilde")
    for FG in ((toy.F, toy.G), (_Z(toy), None)):
        ocp = baseline_psf_problem(toy.sys, toy.Theta0, W_tilde, toy.X0, *FG, toy.K, N)
        for x, u_p, f_ref, v_ref in BASELINE_REF:
            for tg in TARGETS:
                sol = compile(ocp, tg).solve({"x0": np.array(x), "u_p": np.array([u_p])})
                assert sol.status == "optimal", tg
                assert abs(sol.objective - f_ref) <= 1e-6 * f_ref, (tg, sol.objective)
                assert abs(sol["v"][0, 0] - v_ref) <= 1e-5, (tg, sol["v"][0, 0])


def test_dropping_the_block_changes_the_optimum(toy) -> None:
    """Negative control: without the (4.5d) rows the first stored optimum is not reached
    (so the tests above see the block)."""
    ocp = rapsf_problem(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, vertices=toy.V)
    ocp.blocks = [b for b in ocp.blocks if b.name != "tube_constraints"]
    x, u_p, f_ref, _ = RAPSF_REF[0]
    sol = compile(ocp, "exact").solve({"x0": np.array(x), "u_p": np.array([u_p])})
    assert sol.status == "optimal" and sol.objective < f_ref - 1.0


def test_rapsf_controller_takes_the_set(toy) -> None:
    """Algorithm 4.1 built with 𝒵 as a set (``G=None``) runs the same closed loop as with
    the matrices; a 𝒵 that does not fit the system is refused at construction."""
    from balustrade.control.rapsf import RAPSF

    a = RAPSF(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, toy.Theta0,
              target="fast-convex")
    b = RAPSF(toy.sys, toy.X0, _Z(toy), None, toy.W, toy.K, N, toy.Theta0,
              target="fast-convex")
    x, theta = np.array([1.5, 1.0]), np.array([1.2, 0.3])
    for k in range(6):
        u_p = np.array([3.0 * np.cos(k)])
        (ua, ia), (ub, ib) = a.step(x, u_p), b.step(x, u_p)
        assert ia.fallback == ib.fallback and ia.status == ib.status == "ok", (k, ia, ib)
        np.testing.assert_allclose(ua, ub, atol=1e-9)
        assert _Z(toy).contains_pair(x, ua, tol=1e-6)
        x = toy.sys.step(x, ua, theta)
    with pytest.raises(ShapeError, match="F"):
        RAPSF(toy.sys, toy.X0, JointPolytope(np.ones((3, 3)), np.ones((3, 1))), None, toy.W,
              toy.K, N, toy.Theta0)


# -- the block on a plain horizon problem: all backends, against hand-written rows -----------
def _double_integrator_ocp(block: str) -> OCP:
    sys_ = LinearSystem([[1.0, 0.1], [0.0, 1.0]], [[0.005], [0.1]], name="di")
    ocp = OCP(sys_, 6, name=f"di_{block}")
    x0 = ocp.parameter("x0", 2)
    ocp.initial_state(x0)
    ocp.dynamics()
    # 𝒵: x1 + 0.5 u <= 1, −x2 + u <= 2, −u <= 4 (a coupled row and an input-only row)
    F = np.array([[1.0, 0.0], [0.0, -1.0], [0.0, 0.0]])
    G = np.array([[0.5], [1.0], [-1.0]])
    h = np.array([1.0, 2.0, 4.0])
    K = np.array([[-1.0, -1.5]])
    E = Box.symmetric(0.05, 2, name="E")
    Z = JointPolytope(F, G, h)
    if block == "language":
        ocp.joint_constraint(Z, tightening=[0.0, 0.1, 0.1, 0.2, 0.2, 0.2])
        joint_constraint(ocp, Z, feedback=K, tube=E, name="joint_tube")
    else:
        Fn, Gn = F / h[:, None], G / h[:, None]
        t = np.array([E.support(r) for r in Fn + Gn @ K])
        d = [0.0, 0.1, 0.1, 0.2, 0.2, 0.2]
        ocp.le(ca.horzcat(*[ca.mtimes(ca.DM(Fn), ocp.x[:, i]) + ca.mtimes(ca.DM(Gn),
                                                                           ocp.u[:, i]) + d[i]
                            for i in range(6)]), 1.0)
        ocp.le(ca.horzcat(*[ca.mtimes(ca.DM(Fn + Gn @ K), ocp.x[:, i]) + ca.DM(t)
                            + ca.mtimes(ca.DM(Gn), ocp.u[:, i]) for i in range(6)]), 1.0)
    ocp.minimize(squared_norm(ocp.x[0, 1:] - 3.0) + 0.01 * squared_norm(ocp.u))
    return ocp


def test_block_agrees_across_backends_and_with_hand_rows() -> None:
    lang, hand = _double_integrator_ocp("language"), _double_integrator_ocp("hand")
    x0 = np.array([0.2, 0.5])
    ref = compile(hand, "exact").solve({"x0": x0})
    assert ref.status == "optimal"
    for tg in TARGETS:
        sol = compile(lang, tg).solve({"x0": x0})
        assert sol.status == "optimal", tg
        assert abs(sol.objective - ref.objective) <= 1e-5 * max(1.0, ref.objective), tg
        np.testing.assert_allclose(sol["u"], ref["u"], atol=1e-4)
    # the coupled row is active somewhere (the block constrains the optimum)
    xs, us = ref["x"], ref["u"]
    assert np.max(xs[0, :6] + 0.5 * us[0]) > 0.7


def test_feedback_support_forms_agree(toy) -> None:
    """``t_r`` by LP (polytope), closed form (box, ellipsoid) and over vertices agree."""
    Z = _Z(toy)
    lp = Z.feedback_support(toy.K, toy.X0)
    np.testing.assert_allclose(Z.feedback_support(toy.K, toy.X0, toy.X0.vertices()), lp,
                               atol=1e-9)
    B = Box([-0.3, -0.1], [0.2, 0.4])
    as_poly = Polytope(B.H, B.h)
    np.testing.assert_allclose(Z.feedback_support(toy.K, B),
                               Z.feedback_support(toy.K, as_poly), atol=1e-9)
    E = Ellipsoid(np.diag([4.0, 9.0]))
    D = Z.closed_loop(toy.K)
    np.testing.assert_allclose(Z.feedback_support(toy.K, E),
                               np.sqrt(np.einsum("ij,jk,ik->i", D, np.diag([0.25, 1 / 9]), D)))
    np.testing.assert_allclose(Z.feedback_support(None, B), [B.support(r) for r in Z.F])


def test_product_equals_joint_constraints_and_membership(toy) -> None:
    X, U = Box.symmetric(2.0, 2), Box.symmetric(3.0, 1)
    Z = JointPolytope.product(X, U)
    F, G = joint_constraints(X, U)
    np.testing.assert_array_equal(Z.F, F)
    np.testing.assert_array_equal(Z.G, G)
    assert (Z.nx, Z.nu, Z.n_rows) == (2, 1, 6)
    assert Z.contains_pair([1.9, -2.0], [3.0]) and not Z.contains_pair([1.9, 0.0], [3.1])
    assert Z.support(np.array([1.0, 1.0, 1.0])) == pytest.approx(7.0)   # a polytope in (x, u)
    assert not Z.is_empty()


# -- bad input -------------------------------------------------------------------------------
def test_bad_input_names_the_argument_and_shapes(toy) -> None:
    with pytest.raises(ShapeError, match=r"G.*\(3, n\).*\(2, 1\)"):
        JointPolytope(np.eye(3)[:, :2], np.ones((2, 1)))
    with pytest.raises(NonFiniteError, match="F"):
        JointPolytope([[np.nan, 0.0]], [[1.0]])
    with pytest.raises(NonFiniteError, match="G"):
        JointPolytope([[1.0, 0.0]], [[np.inf]])
    with pytest.raises(ShapeError, match="h"):
        JointPolytope(np.eye(2), np.ones((2, 1)), h=[1.0, 2.0, 3.0])
    with pytest.raises(BalustradeError, match="positive"):
        JointPolytope(np.eye(2), np.ones((2, 1)), h=[1.0, -2.0])
    with pytest.raises(ShapeError, match="G"):
        JointPolytope(np.eye(2), np.zeros((2, 0)))
    with pytest.raises(BalustradeError, match="origin"):
        JointPolytope.product(Box([0.5, -1.0], [1.0, 1.0]), Box.symmetric(1.0, 1))
    with pytest.raises(BalustradeError, match="Polytope"):
        JointPolytope.product(Ellipsoid(np.eye(2)), Box.symmetric(1.0, 1))
    # 𝒵 of the wrong dimensions for the system: the error names F (or G) and both shapes
    Z3 = JointPolytope(np.ones((4, 3)), np.ones((4, 1)))
    with pytest.raises(ShapeError, match=r"F.*3 columns|F.*2 columns"):
        rapsf_problem(toy.sys, toy.X0, Z3, None, toy.W, toy.K, N, vertices=toy.V)
    Zu = JointPolytope(np.ones((4, 2)), np.ones((4, 2)))
    with pytest.raises(ShapeError, match=r"G"):
        baseline_psf_problem(toy.sys, toy.Theta0, Box.symmetric(0.01, 2), toy.X0, Zu, None,
                             toy.K, N)
    with pytest.raises(ShapeError, match=r"G.*\(6, n\)"):
        rapsf_problem(toy.sys, toy.X0, toy.F, toy.G[:4], toy.W, toy.K, N, vertices=toy.V)
    with pytest.raises(BalustradeError, match="not both"):
        as_joint(_Z(toy), toy.G, "here")
    with pytest.raises(BalustradeError, match="G is missing"):
        rapsf_problem(toy.sys, toy.X0, toy.F, None, toy.W, toy.K, N, vertices=toy.V)


def test_block_bad_input(toy) -> None:
    sys_ = LinearSystem(np.eye(2), np.ones((2, 1)))
    ocp = OCP(sys_, 3, name="o")
    Z = _Z(toy)
    with pytest.raises(BalustradeError, match="JointPolytope"):
        ocp.joint_constraint(Box.symmetric(1.0, 3))
    with pytest.raises(ShapeError, match="F"):
        ocp.joint_constraint(JointPolytope(np.ones((2, 3)), np.ones((2, 1))))
    with pytest.raises(ShapeError, match="K"):
        ocp.joint_constraint(Z, feedback=np.ones((2, 2)))
    with pytest.raises(BalustradeError, match="tube"):
        ocp.joint_constraint(Z, tube="X0")
    with pytest.raises(ShapeError, match="alpha"):
        ocp.joint_constraint(Z, feedback=toy.K, tube=(ca.SX.sym("a", 1, 2), toy.X0))
    with pytest.raises(ShapeError, match="dimension 2"):
        ocp.joint_constraint(Z, feedback=toy.K, tube=Box.symmetric(1.0, 3))
    with pytest.raises(BalustradeError, match="steps"):
        ocp.joint_constraint(Z, steps=[0, 3])
    with pytest.raises(BalustradeError, match="unbounded"):
        ocp.joint_constraint(Z, feedback=toy.K, tube=Box([-1.0, -np.inf], [1.0, 1.0]))
    with pytest.raises(BalustradeError, match="SX"):
        ocp.joint_constraint(Z, x=np.zeros((2, 3)), u=ocp.u)
    assert not [b for b in ocp.blocks if b.tag == "state"]       # nothing half-added
