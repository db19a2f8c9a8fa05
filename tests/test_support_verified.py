"""Support functions of a general polytope are verified upper bounds (session 13, audit
finding 5): ``Polytope.support`` raises the LP optimum to its weak-duality bound over a box
that provably contains the set, so the tube constants ``s_jr``, ``t_r`` of SPEC §2.20
(s_constants, tube_constants, check_rpi, check_constraints) and the row screening of
contractive_polytope never under-estimate."""

from __future__ import annotations

import numpy as np
import scipy.optimize

from balustrade.design.rapsf import Parallelotope, _supports
from balustrade.dsl import sets_geometry as geo
from balustrade.dsl.sets import Polytope
from balustrade.problems.rapsf import closed_loop_matrices, s_constants
from balustrade.reproduce import msd_adaptive as M

#: rounding of the closed form |aᵀT⁻¹| d itself
ROUNDING = 1e-12


def test_eight_mass_x0_as_a_plain_polytope_is_never_below_the_closed_form():
    """The auditor's a14 case: the 8-mass parallelotope 𝕏₀ written as a plain Polytope;
    the LP optima were up to 2.8e-7 below ``‖a M‖₁``."""
    d = M.design(8)
    X0, sysm, K = d["X0"], d["system"], d["K"]
    P = Polytope(X0.H, X0.h)
    V = d["setup"].Theta0.vertices()[::16]
    S_lp = s_constants(P, sysm, K, V)
    HX = X0.H / X0.h[:, None]
    Mm = X0.support_l1_map()
    S_ex = np.column_stack([np.abs(HX @ A @ Mm).sum(axis=1)
                            for A in closed_loop_matrices(sysm, K, V)])
    assert np.all(S_lp >= S_ex - ROUNDING), (S_ex - S_lp).max()
    assert np.all(S_lp - S_ex <= 1e-6)                   # and still tight


def _random_parallelotope(seed: int, n: int = 16) -> Parallelotope:
    rng = np.random.default_rng(seed)
    T = rng.normal(size=(n, n)) @ np.diag(np.logspace(0, 2.5, n)) @ rng.normal(size=(n, n))
    return Parallelotope(T, rng.uniform(0.5, 2.0, n))


def test_random_polytope_supports_and_box_screen_are_upper_bounds():
    X = _random_parallelotope(0)
    P = Polytope(X.H, X.h)
    A = np.random.default_rng(1).normal(size=(20, X.dim))
    exact = np.array([X.support(a) for a in A])
    got = np.array([P.support(a) for a in A])
    assert np.all(got >= exact - ROUNDING * (1 + np.abs(exact)))
    assert np.all(got - exact <= 1e-6 * (1 + np.abs(exact)))
    # contractive_polytope's screening: the same bounds through the warm-started LPs
    unit = Polytope(X.H / X.h[:, None], np.ones(X.H.shape[0]))
    _, values = _supports(unit, list(A), 1e-9)
    assert np.all(values >= exact - ROUNDING * (1 + np.abs(exact)))


def test_verified_box_holds_for_any_multipliers():
    """Weak duality only: perturbed (even poor) multipliers still give a box containing
    every vertex of a known parallelotope; missing or useless ones give ``None``."""
    X = _random_parallelotope(2, n=4)
    H, h = X.H, X.h
    n = X.dim
    ys = []
    for sign in (1.0, -1.0):
        for i in range(n):
            c = np.zeros(n)
            c[i] = -sign
            res = scipy.optimize.linprog(c, A_ub=H, b_ub=h, bounds=[(None, None)] * n,
                                         method="highs")
            ys.append(-res.ineqlin.marginals)
    rng = np.random.default_rng(3)
    noisy = [y + 1e-4 * rng.uniform(0, 1, y.size) for y in ys]
    lb, ub = geo.box_from_multipliers(H, h, noisy[:n], noisy[n:])
    corners = np.array(np.meshgrid(*[[-1, 1]] * n)).reshape(n, -1).T * X.d
    V = corners @ X.T_inv.T                                # vertices x = T⁻¹ y
    assert np.all(V >= lb[None, :] - 1e-12) and np.all(V <= ub[None, :] + 1e-12)
    assert np.all(np.isfinite(lb)) and np.all(np.isfinite(ub))
    lb, ub = geo.box_from_multipliers(H, h, ys[:n], ys[n:])   # the LP's own: tight
    assert np.all(np.abs(ub - V.max(axis=0)) < 1e-6) and np.all(np.abs(lb - V.min(axis=0)) < 1e-6)
    assert geo.box_from_multipliers(H, h, [None] * n, ys[n:]) is None
    assert geo.box_from_multipliers(H, h, [0 * y for y in ys[:n]], ys[n:]) is None
    assert geo.verified_box(np.eye(2)[:1], np.ones(1)) is None   # unbounded
