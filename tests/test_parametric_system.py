"""ParametricLinearSystem (model (4.6), SPEC §2.19): A(θ), B(θ), the regressor D(x, u), step,
the nominal LinearSystem, the System with θ as parameter, and bad input."""

from __future__ import annotations

import numpy as np
import pytest

from balustrade.dsl import LinearSystem, ParametricLinearSystem
from balustrade.errors import BalustradeError, ShapeError

RNG = np.random.default_rng(0)
A0, B0 = RNG.normal(size=(3, 3)), RNG.normal(size=(3, 2))
AS = [RNG.normal(size=(3, 3)) for _ in range(2)]
BS = [RNG.normal(size=(3, 2)) for _ in range(2)]


def make() -> ParametricLinearSystem:
    return ParametricLinearSystem(A0, AS, B0, BS, name="p")


def test_shapes_and_affine_maps():
    s = make()
    assert (s.nx, s.nu, s.nw, s.q) == (3, 2, 3, 2)
    th = np.array([0.3, -1.2])
    np.testing.assert_allclose(s.A(th), A0 + 0.3 * AS[0] - 1.2 * AS[1])
    np.testing.assert_allclose(s.B(th), B0 + 0.3 * BS[0] - 1.2 * BS[1])


def test_regressor_makes_the_successor_affine_in_theta():
    s = make()
    x, u, th, w = RNG.normal(size=3), RNG.normal(size=2), RNG.normal(size=2), RNG.normal(size=3)
    D = s.D(x, u)
    assert D.shape == (3, 2)
    np.testing.assert_allclose(D[:, 1], AS[1] @ x + BS[1] @ u)
    np.testing.assert_allclose(s.step(x, u, th, w), s.affine_part(x, u) + D @ th + w)
    np.testing.assert_allclose(s.step(x, u, th), s.A(th) @ x + s.B(th) @ u)


def test_nominal_and_as_system_agree_with_step():
    s = make()
    x, u, th, w = RNG.normal(size=3), RNG.normal(size=2), RNG.normal(size=2), RNG.normal(size=3)
    nom = s.nominal(th)
    assert isinstance(nom, LinearSystem)
    np.testing.assert_allclose(nom.step(x, u, w), s.step(x, u, th, w))
    sym = s.as_system()
    assert sym.ntheta == 2
    np.testing.assert_allclose(sym.step(x, u, w, th), s.step(x, u, th, w))


def test_missing_B_list_means_zero():
    s = ParametricLinearSystem(A0, AS, B0, None)
    np.testing.assert_allclose(s.B(np.array([5.0, 7.0])), B0)


@pytest.mark.parametrize("kwargs,match", [
    (dict(A_list=[np.eye(2)]), r"A_list\[0\].*\(3, 3\).*\(2, 2\)"),
    (dict(B_list=[np.zeros((3, 2))]), r"B_list.*2 matrices"),
    (dict(A_list=None, B_list=None), "both None"),
    (dict(A_list=[], B_list=[]), "q >= 1"),
    (dict(A_list="A"), "list of q matrices"),
    (dict(E=np.eye(2)), r"E.*\(3, None\)|E.*3"),
])
def test_bad_input_names_the_argument_and_shapes(kwargs, match):
    args = dict(A0=A0, A_list=AS, B0=B0, B_list=BS)
    args.update(kwargs)
    with pytest.raises(BalustradeError, match=match):
        ParametricLinearSystem(**args)


def test_bad_theta_shape():
    with pytest.raises(ShapeError, match=r"p.step: theta"):
        make().step(np.zeros(3), np.zeros(2), np.zeros(3))


# -- the mass-spring-damper chain of Section 4.7 (SPEC §3.2) ---------------------------------
def test_msd_chain_matches_the_printed_equations():
    from balustrade.models.msd import msd_chain

    n, Ts, d = 3, 0.2, 0.1
    s = msd_chain(n)
    assert (s.nx, s.nu, s.q) == (6, 3, 2)
    rng = np.random.default_rng(3)
    x, u, th = rng.normal(size=6), rng.normal(size=3), rng.uniform(0.05, 0.25, size=2)
    p, v = x[:n], x[n:]
    c = np.concatenate([[0.0], th, [0.0]])        # c_{0,1}, c_{1,2}, c_{2,3}, c_{3,4}
    dd = np.array([0.0, d, d, 0.0])
    pe, ve = np.concatenate([[0.0], p, [0.0]]), np.concatenate([[0.0], v, [0.0]])
    want = np.empty(6)
    for i in range(1, n + 1):
        want[i - 1] = p[i - 1] + Ts * v[i - 1]
        want[n + i - 1] = (v[i - 1] - Ts * c[i - 1] * (pe[i] - pe[i - 1])
                           - Ts * dd[i - 1] * (ve[i] - ve[i - 1])
                           + Ts * c[i] * (pe[i + 1] - pe[i])
                           + Ts * dd[i] * (ve[i + 1] - ve[i]) + u[i - 1])
    # free ends: the terms with c_{0,1}, c_{n,n+1} vanish whatever pe[0], pe[n+1] are
    np.testing.assert_allclose(s.step(x, u, th), want, atol=1e-14)


def test_msd_setup_and_performance_controller():
    from balustrade.models.msd import msd_performance, msd_setup

    st = msd_setup(3)
    assert st.constraint_volume() == pytest.approx(9474.3, abs=0.05)
    assert msd_setup(8).constraint_volume() == pytest.approx(4.019e10, rel=1e-3)
    np.testing.assert_allclose(st.Theta0.lb, [0.05, 0.05])
    np.testing.assert_allclose(st.W.ub, 1e-3 * np.ones(6))
    # r_5 = 2.5 > X's 2.3: the proposal saturates at U's bound on mass 1 only
    np.testing.assert_allclose(msd_performance(5, np.zeros(6), 3), [3.5, 0.0, 0.0])
    np.testing.assert_allclose(msd_performance(30, np.r_[0.0, 0, 0, 0.5, 0, 0], 3),
                               [-3.5, 0.0, 0.0])
