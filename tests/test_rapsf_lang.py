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


# -- the offline design takes 𝒵 as a set too (issue #15 §3) -----------------------------------
def test_design_functions_take_the_set(toy) -> None:
    """Every design function of Chapter 4 (tube shape, the checks of Assumption 4.11 with the
    default, an H-representation and a hull terminal set) gives the same result with 𝒵 as
    ``(F, G)`` and as a ``JointPolytope``."""
    from balustrade.design.rapsf import (
        check_assumption_4_11,
        check_constraints,
        contractive_parallelotope,
        contractive_polytope,
    )
    from balustrade.design.rapsf_enlarge import check_enlarged_terminal
    from balustrade.problems.rapsf import TerminalSet

    Z = _Z(toy)
    a = contractive_polytope(toy.sys, toy.K, toy.V, toy.W, toy.F, toy.G)
    b = contractive_polytope(toy.sys, toy.K, toy.V, toy.W, Z)
    np.testing.assert_array_equal(a.H, b.H)
    np.testing.assert_array_equal(a.h, b.h)
    a = contractive_parallelotope(toy.sys, toy.K, toy.V, toy.W, toy.F, toy.G)
    b = contractive_parallelotope(toy.sys, toy.K, toy.V, toy.W, Z)
    np.testing.assert_array_equal(a.H, b.H)
    ra, rb = check_constraints(toy.X0, toy.F, toy.G, toy.K), check_constraints(toy.X0, Z, None,
                                                                                toy.K)
    assert ra.ok and rb.ok and ra.worst == rb.worst
    np.testing.assert_array_equal(ra.details["t"], rb.details["t"])
    H_T = np.vstack([np.eye(2), -np.eye(2)])          # |z| <= 0.05 (1 − α): a small cone
    terminals = [None, TerminalSet(H_T / 0.05, np.ones(4)),
                 TerminalSet.from_generators(np.zeros((2, 1)), np.array([0.5]))]
    for terminal in terminals:
        ra = check_assumption_4_11(toy.sys, toy.X0, toy.W, toy.K, toy.V, toy.F, toy.G, terminal)
        rb = check_assumption_4_11(toy.sys, toy.X0, toy.W, toy.K, toy.V, Z, terminal=terminal)
        assert ra.ok == rb.ok and ra.worst == rb.worst, terminal
    ta = check_enlarged_terminal(toy.sys, toy.X0, toy.W, toy.K, toy.V, toy.F, toy.G,
                                 terminals[2])
    tb = check_enlarged_terminal(toy.sys, toy.X0, toy.W, toy.K, toy.V, Z, None, terminals[2])
    assert ta.ok and tb.ok
    np.testing.assert_array_equal(ta.details["violations"], tb.details["violations"])


def test_design_functions_bad_joint_constraints(toy) -> None:
    """A 𝒵 that does not fit the system, or half of the matrix spelling, is refused with a
    BalustradeError naming the argument (and the shapes) before any LP."""
    from balustrade.design.rapsf import (
        check_assumption_4_11,
        check_constraints,
        contractive_box,
        contractive_polytope,
    )
    from balustrade.design.rapsf_enlarge import check_enlarged_terminal
    from balustrade.problems.rapsf import TerminalSet

    Z3 = JointPolytope(np.ones((4, 3)), np.ones((4, 1)))
    with pytest.raises(ShapeError, match=r"contractive_polytope.*F.*2 columns.*\(4, 3\)"):
        contractive_polytope(toy.sys, toy.K, toy.V, toy.W, Z3)
    with pytest.raises(ShapeError, match=r"contractive_box.*G.*\(6, n\).*\(4, 1\)"):
        contractive_box(toy.sys, toy.K, toy.V, toy.W, toy.F, toy.G[:4])
    with pytest.raises(BalustradeError, match="G is missing"):
        check_constraints(toy.X0, toy.F, None, toy.K)
    with pytest.raises(BalustradeError, match="not both"):
        check_assumption_4_11(toy.sys, toy.X0, toy.W, toy.K, toy.V, _Z(toy), toy.G)
    with pytest.raises(ShapeError, match=r"check_constraints.*G.*1 columns.*\(6, 2\)"):
        check_constraints(toy.X0, JointPolytope(toy.F, np.ones((6, 2))), None, toy.K)
    with pytest.raises(ShapeError, match=r"check_assumption_4_11: K"):
        check_assumption_4_11(toy.sys, toy.X0, toy.W, np.ones((2, 2)), toy.V, _Z(toy))
    with pytest.raises(ShapeError, match=r"check_enlarged_terminal.*F.*2 columns"):
        check_enlarged_terminal(toy.sys, toy.X0, toy.W, toy.K, toy.V, Z3, None,
                                TerminalSet.from_generators(np.zeros((2, 1)), np.ones(1)))


def test_msd_adaptive_takes_the_set_or_the_matrices() -> None:
    """``reproduce msd-adaptive``'s design holds 𝒵 as a ``JointPolytope`` (``d["Z"]``); a design
    with only the matrices ``F, G`` (the older spelling) runs the same closed loop and the
    same feasibility sets, and matrices that do not fit the system are refused naming them."""
    from balustrade.reproduce import msd_adaptive as M

    d = M.design(2, steps=6)
    assert isinstance(d["Z"], JointPolytope)
    np.testing.assert_array_equal(d["F"], d["Z"].F)
    only_z = {k: v for k, v in d.items() if k not in ("F", "G")}
    only_fg = {k: v for k, v in d.items() if k != "Z"}
    rng = np.random.default_rng(0)
    s = d["setup"]
    theta = s.sample_theta(rng)
    ws = rng.uniform(s.W.lb, s.W.ub, size=(6, 4))
    runs = [M.closed_loop(M.adaptive_controller(dd), dd, theta, ws) for dd in (only_z, only_fg)]
    np.testing.assert_array_equal(runs[0]["inputs"], runs[1]["inputs"])
    assert runs[0]["worst_z"] == runs[1]["worst_z"] and runs[0]["z_ok"]
    xs = rng.uniform(s.X.lb, s.X.ub, size=(5, 4))
    outs = [M.feasibility_sets(dd, None, s.Theta0, None)["F_theta0"].feasible(xs)
            for dd in (only_z, only_fg)]
    np.testing.assert_array_equal(outs[0], outs[1])
    with pytest.raises(ShapeError, match=r"d\['F'\], d\['G'\].*G.*\(6, n\)|G.*\(\d+, n\)"):
        M.adaptive_controller({**only_fg, "G": only_fg["G"][:3]})
    with pytest.raises(ShapeError, match=r"d\['Z'\].*F.*4 columns"):
        M.closed_loop(None, {**only_z, "Z": JointPolytope(np.ones((2, 3)), np.ones((2, 2)))},
                      theta, ws)
    with pytest.raises(BalustradeError, match="no joint constraints"):
        M.adaptive_controller({k: v for k, v in only_fg.items() if k not in ("F",)})
