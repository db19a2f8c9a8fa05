"""``Set.project``: the one exact Euclidean projection onto a set (boxes, polytopes,
ellipsoids), checked against a conic solver and the KKT conditions."""

from __future__ import annotations

import cvxpy as cp
import numpy as np
import pytest

from balustrade.control.fallbacks import project
from balustrade.dsl.sets import Box, Ellipsoid, FunctionSet, Polytope
from balustrade.errors import BalustradeError, ShapeError


def reference(S, u: np.ndarray) -> np.ndarray:
    v = cp.Variable(u.size)
    cons = [S.H @ v <= S.h] if isinstance(S, Polytope) else \
        [cp.quad_form(v - S.center, S.P) <= 1]
    cp.Problem(cp.Minimize(cp.sum_squares(v - u)), cons).solve(solver="CLARABEL")
    return np.asarray(v.value).reshape(-1)


def random_polytope(rng: np.random.Generator, n: int, m: int) -> Polytope:
    H = rng.standard_normal((m, n))
    return Polytope(H, np.abs(rng.standard_normal(m)) + 0.1 + H @ rng.standard_normal(n) * 0.3)


def test_box_projection_is_a_clip():
    B = Box(np.array([-1.0, -np.inf]), np.array([2.0, 1.0]))
    assert np.array_equal(B.project([5.0, -7.0]), [2.0, -7.0])
    assert np.array_equal(B.project([0.5, 3.0]), [0.5, 1.0])


@pytest.mark.parametrize("n,m", [(1, 2), (2, 3), (2, 7), (3, 10), (5, 12)])
def test_polytope_projection_matches_a_qp(n, m):
    rng = np.random.default_rng(n * 100 + m)
    for _ in range(20):
        S = random_polytope(rng, n, m)
        u = 3.0 * rng.standard_normal(n)
        x = S.project(u)
        assert S.contains(x, tol=1e-10)
        ref = reference(S, u)
        assert np.linalg.norm(x - u) <= np.linalg.norm(ref - u) + 1e-7
        assert np.abs(x - ref).max() <= 1e-5
        # optimality: u − x is in the normal cone (no feasible point closer along a chord)
        for y in (S.project(3.0 * rng.standard_normal(n)) for _ in range(5)):
            assert (u - x) @ (y - x) <= 1e-9 * (1.0 + np.linalg.norm(u - x)
                                                * np.linalg.norm(y - x))


def test_polytope_projection_of_an_interior_point_is_the_point():
    S = Polytope(np.array([[1.0, 1.0], [-1.0, 0.0], [0.0, -1.0]]), np.array([1.0, 0.0, 0.0]))
    assert np.array_equal(S.project([0.2, 0.3]), [0.2, 0.3])
    assert S.project([2.0, 2.0]) == pytest.approx([0.5, 0.5], abs=1e-12)
    assert S.project([-1.0, 3.0]) == pytest.approx([0.0, 1.0], abs=1e-12)


def test_a_non_box_set_is_not_projected_by_clipping():
    """The old copy clipped to the bounding box: for this triangle that point is outside."""
    S = Polytope(np.array([[-1.0, -1.0], [1.0, 0.0], [0.0, 1.0]]), np.array([-1.0, 2.0, 2.0]))
    bb = S.bounding_box()
    u = np.array([-3.0, -3.0])
    assert not S.contains(np.clip(u, bb.lb, bb.ub))
    assert S.project(u) == pytest.approx([0.5, 0.5], abs=1e-12)
    assert project(u, S) == pytest.approx([0.5, 0.5], abs=1e-12)


def test_ellipsoid_projection_matches_a_socp_and_lies_on_the_boundary():
    rng = np.random.default_rng(5)
    for n in (1, 2, 4):
        for _ in range(10):
            L = rng.standard_normal((n, n))
            E = Ellipsoid(L @ L.T + 0.1 * np.eye(n), rng.standard_normal(n))
            u = E.center + 4.0 * rng.standard_normal(n)
            x = E.project(u)
            d = x - E.center
            if (u - E.center) @ E.P @ (u - E.center) <= 1.0:
                assert np.array_equal(x, u)
                continue
            assert d @ E.P @ d == pytest.approx(1.0, abs=1e-12)  # on the boundary
            ref = reference(E, u)
            assert np.linalg.norm(x - u) <= np.linalg.norm(ref - u) + 1e-6  # ref: solver tol
            assert np.abs(x - ref).max() <= 1e-4
            # KKT: u − x = λ P (x − q) with λ >= 0
            g = E.P @ d
            lam = (u - x) @ g / (g @ g)
            assert lam >= 0 and np.abs(u - x - lam * g).max() <= 1e-9 * (1 + abs(lam))


def test_projection_checks_its_argument_and_refuses_sets_without_one():
    S = Box.symmetric([1.0, 1.0])
    with pytest.raises(ShapeError):
        S.project(np.zeros(3))
    with pytest.raises(BalustradeError):
        S.project([np.nan, 0.0])
    F = FunctionSet(lambda x: x[0] ** 2 - 1, 1, name="F")
    with pytest.raises(BalustradeError, match="no exact projection"):
        F.project([2.0])
    assert project(np.array([2.0]), F)[0] == 2.0  # the loop's fallback never raises
