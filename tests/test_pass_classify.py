"""The classify pass: affine, convex quadratic and jointly quadratic rows; refusals."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from balustrade.backends.passes import CVXPY_CHAIN, Classify, run_chain
from balustrade.backends.passes.classify import Affine, JointQuadratic, Quadratic
from balustrade.dsl import OCP, norm
from balustrade.errors import ConvexityError


def _ocp():
    ocp = OCP(name="cls")
    z = ocp.variable("z", 2)
    x = ocp.parameter("x", 2)
    return ocp, z, x


def test_affine_block_is_one_piece():
    ocp, z, x = _ocp()
    ocp.le(ca.vertcat(z[0] + 2 * x[1] - 1, -z[1]), name="lin")
    (cb,) = Classify().apply(ocp)[0].blocks
    (piece,) = cb.pieces
    assert isinstance(piece.form, Affine) and not cb.conic
    np.testing.assert_array_equal(piece.rows, [0, 1])
    np.testing.assert_array_equal(piece.form.A.toarray(), [[1, 0], [0, -1]])
    np.testing.assert_array_equal(piece.form.B.toarray(), [[0, 2], [0, 0]])
    np.testing.assert_array_equal(piece.form.c, [-1, 0])


def test_mixed_block_quadratic_rows_first_then_affine_rows_stacked():
    ocp, z, x = _ocp()
    P = np.array([[2.0, 0.5], [0.5, 1.0]])
    e = x - z
    ocp.le(ca.vertcat(z[0] - 1, ca.mtimes([e.T, P, e]) - 1, ca.sumsqr(z) - ca.sin(x[0]), z[1]),
           name="mixed")
    cls, _ = Classify().apply(ocp)
    pieces = cls.blocks[0].pieces
    assert [type(pc.form) for pc in pieces] == [JointQuadratic, Quadratic, Affine]
    assert [pc.rows.tolist() for pc in pieces] == [[1], [2], [0, 3]]
    jq = pieces[0].form  # kept about its centre: ½‖L_w z + L_p x + l‖² + c with c = −1
    assert jq.linear_free and jq.c == pytest.approx(-1.0)
    zv, xv = np.array([0.3, -0.2]), np.array([100.0, -50.0])
    v = jq.Lw @ zv[jq.w_index] + jq.Lp @ xv[jq.p_index] + jq.l
    assert 0.5 * v @ v + jq.c == pytest.approx((xv - zv) @ P @ (xv - zv) - 1, rel=1e-12)
    assert pieces[1].form.phi is not None  # −sin(x₀): a derived parameter for cvxpy
    assert cls.conic


def test_refusals_name_the_block():
    ocp, z, x = _ocp()
    ocp.eq(z[0] ** 2 - x[0], name="circle")
    with pytest.raises(ConvexityError, match="block 'circle'.*equality.*must be affine"):
        Classify().apply(ocp)
    ocp, z, x = _ocp()
    ocp.le(-ca.sumsqr(z), name="concave")
    with pytest.raises(ConvexityError, match="block 'concave', row 0.*negative eigenvalue"):
        Classify().apply(ocp)
    ocp, z, x = _ocp()
    ocp.minimize(norm(ca.sin(z), 1, label="wavy"))
    with pytest.raises(ConvexityError, match="cost term 'wavy'.*must be affine"):
        Classify().apply(ocp)


def test_cost_terms_and_chain():
    ocp, z, x = _ocp()
    ocp.le(z - 1, name="box")
    ocp.minimize(norm(z - x, 2) + ca.sumsqr(z))
    cls, _ = Classify().apply(ocp)
    assert [type(t.form) for t in cls.terms] == [Affine, Quadratic]
    assert cls.conic  # a 2-norm cost needs a cone
    program, _ = run_chain(CVXPY_CHAIN, ocp)
    assert program.conic and set(program.block_constraints) == {"box"}
    assert program.problem.is_dpp()


@pytest.mark.parametrize("target", ["cvxpy", "fast-convex"])
def test_refusal_names_the_direct_backend_too(target):
    """The pass is shared by both convex backends; its message said "the cvxpy backend" also
    when the user compiled for ``fast-convex`` (session 15 docs audit)."""
    from balustrade.backends import compile

    ocp, z, x = _ocp()
    ocp.eq(z[0] ** 2 - x[0], name="circle")
    ocp.minimize(ca.sumsqr(z))
    with pytest.raises(ConvexityError, match=r"block 'circle'.*convex backends \(cvxpy, direct\)"):
        compile(ocp, target)
