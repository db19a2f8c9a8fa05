"""Unit tests of the set library: closed forms, degenerate cases, errors (SPEC §1.3–1.5)."""

from __future__ import annotations

import warnings

import casadi as ca
import numpy as np
import pytest

from balustrade.dsl.sets import (
    Box,
    Ellipsoid,
    FunctionSet,
    Polytope,
    Set,
    linear_map,
    minkowski_sum,
    pontryagin_difference,
)
from balustrade.errors import (
    BalustradeError,
    EmptySetError,
    NonFiniteError,
    NotPSDError,
    ShapeError,
)

SQUARE = np.vstack([np.eye(2), -np.eye(2)])
TRIANGLE = Polytope(np.array([[-1.0, 0.0], [0.0, -1.0], [1.0, 1.0]]), np.array([0.0, 0.0, 1.0]),
                    name="Tri")


def disk(r: float = 1.0, name: str = "Disk") -> FunctionSet:
    return FunctionSet(lambda x: x[0] ** 2 + x[1] ** 2 - r**2, 2, name=name)


# -- bad input: the right exception, naming the set -------------------------------------------

def test_polytope_bad_input_names_the_set() -> None:
    with pytest.raises(NonFiniteError, match="Xset"):
        Polytope(np.array([[1.0, np.nan]]), np.array([1.0]), name="Xset")
    with pytest.raises(NonFiniteError, match="Xset"):
        Polytope(np.array([[1.0, 0.0]]), np.array([np.inf]), name="Xset")
    with pytest.raises(ShapeError, match="Xset") as exc:
        Polytope(SQUARE, np.ones(3), name="Xset")
    assert exc.value.expected == (4,) and exc.value.given == (3,)
    with pytest.raises(EmptySetError, match="Xset"):
        Polytope(np.array([[1.0], [-1.0]]), np.array([-1.0, -1.0]), name="Xset")


def test_box_bad_input_names_the_set() -> None:
    with pytest.raises(EmptySetError, match="Ubox.*\\[1\\]"):
        Box([0.0, 2.0], [1.0, 1.0], name="Ubox")
    with pytest.raises(NonFiniteError, match="Ubox"):
        Box([0.0, np.nan], [1.0, 1.0], name="Ubox")
    with pytest.raises(ShapeError, match="Ubox"):
        Box([0.0, 0.0], [1.0, 1.0, 1.0], name="Ubox")
    # an upper bound of -inf (or lower bound of +inf) is empty, not the whole line (bug fix)
    with pytest.raises(EmptySetError, match="Ubox"):
        Box([-np.inf], [-np.inf], name="Ubox")
    with pytest.raises(EmptySetError, match="Ubox"):
        Box([np.inf], [np.inf], name="Ubox")


def test_ellipsoid_bad_input_names_the_set() -> None:
    with pytest.raises(NotPSDError, match="Eset"):
        Ellipsoid(np.diag([1.0, -1.0]), name="Eset")
    with pytest.raises(NotPSDError, match="Eset"):
        Ellipsoid(np.diag([1.0, 0.0]), name="Eset")  # P must be definite
    with pytest.raises(NotPSDError, match="Eset.*symmetric"):
        Ellipsoid(np.array([[1.0, 0.5], [0.0, 1.0]]), name="Eset")
    with pytest.raises(ShapeError, match="Eset"):
        Ellipsoid(np.ones((2, 3)), name="Eset")
    with pytest.raises(ShapeError, match="Eset: center"):
        Ellipsoid(np.eye(2), center=np.zeros(3), name="Eset")
    with pytest.raises(NonFiniteError, match="Eset"):
        Ellipsoid(np.array([[1.0, np.nan], [np.nan, 1.0]]), name="Eset")
    with pytest.raises(NonFiniteError, match="Eset"):
        Ellipsoid(np.eye(2), center=[0.0, np.inf], name="Eset")


def test_tightening_to_empty_names_both_sets() -> None:
    X = Box([-1.0, -1.0], [1.0, 1.0], name="Xbox")
    with pytest.raises(EmptySetError, match="Xbox.*Wbig"):
        X.tighten(Box.symmetric(1.5, 2, name="Wbig"))
    P = Polytope(SQUARE, np.ones(4), name="Xpoly")
    with pytest.raises(EmptySetError, match="Xpoly.*Ebig"):
        P.tighten(Ellipsoid(np.eye(2) / 4.0, name="Ebig"))
    with pytest.raises(EmptySetError, match="Xpoly.*Wbig"):
        pontryagin_difference(P, Box.symmetric(1.5, 2, name="Wbig"))
    # a set unbounded along a row normal empties the difference (was NonFiniteError)
    half = Box([-np.inf, -1.0], [np.inf, 1.0], name="Slab")
    with pytest.raises(EmptySetError, match="Xpoly.*Slab"):
        P.tighten(half)
    with pytest.raises(EmptySetError, match="Xbox.*Slab"):
        X.tighten(half)
    with pytest.raises(ShapeError, match="Xpoly"):
        P.tighten(Box.symmetric(0.1, 3))


def test_operation_errors_name_the_set_and_shapes() -> None:
    P = Polytope(SQUARE, np.ones(4), name="Pset")
    E = Ellipsoid(np.eye(3), name="Eset")
    with pytest.raises(ShapeError, match="Pset.linear_map") as exc:
        P.linear_map(np.ones((2, 3)))
    assert exc.value.given == (2, 3)
    with pytest.raises(NonFiniteError, match="Pset.linear_map"):
        P.linear_map(np.array([[1.0, np.nan], [0.0, 1.0]]))
    with pytest.raises(BalustradeError, match=r"Eset.*\(2, 3\).*rank 1"):
        E.linear_map(np.array([[1.0, 0.0, 0.0], [2.0, 0.0, 0.0]]))
    with pytest.raises(BalustradeError, match=r"Eset.*\(4, 3\)"):
        E.linear_map(np.ones((4, 3)))
    halfplane = Polytope(np.array([[1.0, 0.0]]), np.array([1.0]), name="Half")
    with pytest.raises(BalustradeError, match=r"Half.*\(1, 2\).*unbounded"):
        halfplane.linear_map(np.array([[1.0, 1.0]]))
    with pytest.raises(BalustradeError, match="Half.*unbounded"):
        halfplane.sample(3, 0)
    with pytest.raises(BalustradeError, match="Half"):
        halfplane.chebyshev_center()
    with pytest.raises(BalustradeError, match="Half.*unbounded"):
        halfplane.vertices()
    with pytest.raises(BalustradeError, match="Half.*bounded"):
        halfplane.minkowski_sum(P)
    with pytest.raises(BalustradeError, match="Ubox.*unbounded"):
        Box([-np.inf, 0.0], [0.0, 1.0], name="Ubox").sample(2, 0)
    with pytest.raises(ShapeError, match="Pset ⊕ Eset"):
        P.minkowski_sum(E)
    with pytest.raises(BalustradeError, match="Disk"):
        P.minkowski_sum(disk())
    with pytest.raises(BalustradeError, match="Eset ⊖"):
        E.pontryagin_difference(Ellipsoid(np.eye(3) * 4))
    with pytest.raises(BalustradeError, match="Pset ⊆ Disk"):
        P.is_subset_of(disk())
    with pytest.raises(ShapeError, match="Pset.contains"):
        P.contains(np.zeros(3))
    with pytest.raises(ShapeError, match="Pset.contains_many"):
        P.contains_many(np.zeros((4, 3)))
    with pytest.raises(NonFiniteError, match="Pset.scale"):
        P.scale(np.nan)
    with pytest.raises(BalustradeError, match="Eset.scale"):
        E.scale(0.0)
    with pytest.raises(ShapeError, match="Pset.translate"):
        P.translate(np.zeros(3))
    with pytest.raises(BalustradeError, match="Pset.sample"):
        P.sample(-1, 0)
    with pytest.raises(BalustradeError, match="rng"):
        P.sample(2, "seed")  # type: ignore[arg-type]
    with pytest.raises(BalustradeError, match="Pset.sample.*method"):
        P.sample(2, 0, method="gibbs")
    with pytest.raises(BalustradeError, match=r"Big.*\(1, 7\).*dimension <= 6"):
        Polytope(np.vstack([np.eye(7), -np.eye(7)]), np.ones(14), name="Big").linear_map(
            np.ones((1, 7)))
    big = Box.symmetric(1.0, 7, name="Big")
    with pytest.raises(BalustradeError, match="dimension <= 6"):
        Polytope(big.H, big.h, name="Big7").vertices()


def test_function_set_errors() -> None:
    D = disk(name="Dset")
    with pytest.raises(BalustradeError, match="Dset.sample.*bounds"):
        D.sample(5, 0)
    with pytest.raises(ShapeError, match="Dset.sample"):
        D.sample(5, 0, bounds=Box.symmetric(1.0, 3))
    with pytest.raises(BalustradeError, match="Dset.sample.*tighter bounds"):
        D.sample(5, 0, bounds=Box([5.0, 5.0], [6.0, 6.0]), max_draws=5000)
    with pytest.raises(BalustradeError, match=r"Dset.linear_map.*\(2, 2\)"):
        D.linear_map(np.ones((2, 2)))


# -- bug fixes and semantics kept --------------------------------------------------------------

def test_box_support_with_infinite_bounds_has_no_nan_warning() -> None:
    B = Box([-np.inf, 0.0, -2.0], [np.inf, 1.0, np.inf])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert B.support([1.0, 0.0, 0.0]) == np.inf
        assert B.support([-1.0, 0.0, 0.0]) == np.inf
        assert B.support([0.0, 1.0, -1.0]) == 1.0 + 2.0
        assert B.support([0.0, -1.0, 1.0]) == np.inf
    assert B.H.shape == (3, 3)  # rows only for finite bounds: [x1 - 1; x3 ... ]
    assert not B.is_bounded()
    assert B.bounding_box() is B


def test_box_keeps_row_order_and_tightens_to_a_box() -> None:
    B = Box([-1.0, -2.0], [1.0, 2.0], name="B")
    assert np.allclose(B.H, SQUARE) and np.allclose(B.h, [1, 2, 1, 2])
    W = Ellipsoid(np.diag([100.0, 25.0]), center=[0.05, 0.0], name="W")
    T = B.tighten(W)
    ref = Polytope.tighten(B, W)
    assert isinstance(T, Box)
    assert np.allclose(T.H, ref.H) and np.allclose(T.h, ref.h)
    assert np.allclose(T.lb, [-1 + 0.1 - 0.05, -2 + 0.2]) and np.allclose(T.ub, [1 - 0.15, 1.8])
    assert T.name == "B⊖W"
    U = Box([-np.inf, -1.0], [1.0, np.inf])
    TU = U.tighten(Box.symmetric(0.25, 2))
    assert np.allclose(TU.lb, [-np.inf, -0.75]) and np.allclose(TU.ub, [0.75, np.inf])
    assert TU.H.shape == U.H.shape


# -- closed forms ------------------------------------------------------------------------------

def test_ellipsoid_sum_is_the_min_trace_outer_ellipsoid() -> None:
    E = Ellipsoid(np.diag([4.0, 9.0]), center=[1.0, 0.0])
    twice = E.minkowski_sum(E)  # E ⊕ E = 2E exactly; min-trace bound is tight here
    assert np.allclose(twice.P, E.P / 4) and np.allclose(twice.center, [2.0, 0.0])
    F = Ellipsoid(np.array([[1.0, 0.3], [0.3, 2.0]]))
    S = minkowski_sum(E, F)
    Qa, Qb = E.shape_matrix, F.shape_matrix
    traces = [np.trace((1 + 1 / p) * Qa + (1 + p) * Qb) for p in np.linspace(0.05, 5, 400)]
    assert np.trace(S.shape_matrix) <= min(traces) + 1e-9
    for a in np.random.default_rng(0).standard_normal((20, 2)):
        assert S.support(a) >= E.support(a) + F.support(a) - 1e-12


def test_polytope_plus_ellipsoid_is_the_outer_polytope_with_same_normals() -> None:
    E = Ellipsoid(np.eye(2) * 4.0, center=[0.1, 0.0])
    S = TRIANGLE.minkowski_sum(E)
    assert np.allclose(S.H, TRIANGLE.H)
    assert np.allclose(S.h, TRIANGLE.h + [E.support(r) for r in TRIANGLE.H])
    assert np.allclose(E.minkowski_sum(TRIANGLE).h, S.h)
    B = Box([0.0, 0.0], [1.0, 2.0]).minkowski_sum(E)
    assert isinstance(B, Box)
    assert np.allclose(B.lb, [-0.4, -0.5]) and np.allclose(B.ub, [1.6, 2.5])


def test_linear_maps_closed_forms() -> None:
    B = Box([-1.0, 0.0], [1.0, 2.0], name="B")
    D = np.diag([2.0, -1.0])
    DB = D @ B  # numpy defers to Set.__rmatmul__
    assert isinstance(DB, Box)
    assert np.allclose(DB.lb, [-2, -2]) and np.allclose(DB.ub, [2, 0])
    R = np.array([[0.0, -1.0], [1.0, 0.0]])
    RB = linear_map(R, B)
    assert type(RB) is Polytope and RB.name == "A·B"
    assert np.allclose(np.sort(RB.vertices(), axis=0), np.sort(B.vertices() @ R.T, axis=0))
    E = Ellipsoid(np.diag([1.0, 4.0]), center=[1.0, 1.0])
    proj = np.array([[1.0, 0.0]]) @ E
    assert isinstance(proj, Ellipsoid) and np.allclose(proj.P, [[1.0]])
    assert np.allclose(proj.center, [1.0])
    seg = np.array([[1.0, 1.0], [1.0, 1.0]]) @ Box.symmetric(1.0, 2)  # rank 1: a segment
    V = seg.vertices()
    assert V.shape == (2, 2) and np.allclose(np.sort(V[:, 0]), [-2, 2])
    assert np.allclose(V[:, 0], V[:, 1])
    assert seg.contains([1.0, 1.0]) and not seg.contains([1.0, 0.9], tol=1e-6)


def test_flat_polytopes_vertices_and_samples() -> None:
    seg = Polytope(SQUARE, np.array([1.0, 0.0, 0.0, 0.0]), name="Seg")  # [0,1]×{0}
    V = seg.vertices()
    assert np.allclose(np.sort(V[:, 0]), [0, 1]) and np.allclose(V[:, 1], 0)
    X = seg.sample(2000, 0)
    assert np.allclose(X[:, 1], 0) and 0.45 < X[:, 0].mean() < 0.55
    point = Polytope(SQUARE, np.zeros(4), name="Pt")
    assert np.allclose(point.vertices(), [[0.0, 0.0]])
    assert np.allclose(point.sample(3, 0), 0)
    assert Box([0.0, 0.0], [1.0, 2.0]).scale(0.0).contains([0.0, 0.0])


def test_vertices_merge_degenerate_duplicates() -> None:
    cube = Box.symmetric(1.0, 3)
    H = np.vstack([cube.H, cube.H, [[1.0, 1.0, 1.0]]])  # duplicate rows, a row through a vertex
    P = Polytope(H, np.concatenate([cube.h, cube.h, [3.0]]))
    V = P.vertices()
    assert V.shape == (8, 3)
    assert np.allclose(np.sort(np.abs(V), axis=0), 1.0)


def test_bounding_box_and_chebyshev_center() -> None:
    E = Ellipsoid(np.array([[2.0, 0.5], [0.5, 1.0]]), center=[1.0, -1.0])
    generic = Set.bounding_box(E)  # via support functions
    assert np.allclose(E.bounding_box().lb, generic.lb)
    assert np.allclose(E.bounding_box().ub, generic.ub)
    c, r = E.chebyshev_center()
    assert np.allclose(c, [1.0, -1.0]) and np.isclose(r, 1 / np.sqrt(np.linalg.eigvalsh(E.P)[-1]))
    c, r = TRIANGLE.chebyshev_center()
    assert np.isclose(r, 1 / (2 + np.sqrt(2))) and np.allclose(c, r)
    bb = TRIANGLE.bounding_box()
    assert np.allclose(bb.lb, 0) and np.allclose(bb.ub, 1)
    c, r = Box([0.0, 0.0], [2.0, 4.0]).chebyshev_center()
    assert np.allclose(c, [1.0, 2.0]) and r == 1.0


def test_containment_closed_cases() -> None:
    E = Ellipsoid(np.eye(2))
    assert Box.symmetric(0.7, 2).is_subset_of(E)
    assert not Box.symmetric(0.71, 2).is_subset_of(E)  # corner at radius 1.004
    assert E.is_subset_of(Box.symmetric(1.0, 2))
    assert not E.is_subset_of(Box.symmetric(0.99, 2))
    shifted = Ellipsoid(np.eye(2) * 4.0, center=[0.49, 0.0])  # radius 0.5, touches at 0.99
    assert shifted.is_subset_of(E)
    assert not Ellipsoid(np.eye(2) * 4.0, center=[0.51, 0.0]).is_subset_of(E)
    assert not Box([0.0, 0.0], [np.inf, 0.1]).is_subset_of(E)  # unbounded
    assert not Box([0.0, 0.0], [np.inf, 0.1]).is_subset_of(Box.symmetric(5.0, 2))
    assert Box([0.0, 0.0], [1.0, 0.1]).is_subset_of(Box([0.0, -np.inf], [1.0, np.inf]))
    assert TRIANGLE.is_subset_of(Box([0.0, 0.0], [1.0, 1.0]))
    assert disk(0.5).is_subset_of(Box.symmetric(0.5 + 1e-6, 2))  # NLP support
    assert not disk(0.5).is_subset_of(Box.symmetric(0.49, 2))


def test_nonconvex_function_set_support_is_refused_not_underestimated() -> None:
    """Two unit discs centred at x₁ = −3 and x₁ = 6: the true support along e₁ is 7 (the
    vertices of the discs, independent of any solver). The local NLP from x = 0 found the
    left disc's −2, and ``S ⊆ {x₁ <= 2}`` was answered True (audit B, session 14). A row
    that is not provably convex is refused now; a user's exact support is still used, and
    convex rows (the disk) keep the NLP."""
    import balustrade.backends  # noqa: F401 - registers the NLP support solver

    def lobes(x: ca.SX) -> ca.SX:
        return ca.fmin((x[0] + 3) ** 2 + x[1] ** 2 - 1, (x[0] - 6) ** 2 + x[1] ** 2 - 1)

    S = FunctionSet(lobes, 2, name="lobes")
    with pytest.raises(BalustradeError, match=r"lobes.support: row 0 .* not provably convex"):
        S.support(np.array([1.0, 0.0]))
    with pytest.raises(BalustradeError, match="not provably convex"):
        S.is_subset_of(Box([-5.0, -2.0], [2.0, 2.0]))
    exact = FunctionSet(lobes, 2, name="lobes", support=lambda fs, a: float(max(
        a @ c + np.linalg.norm(a) for c in (np.array([-3.0, 0.0]), np.array([6.0, 0.0])))))
    assert exact.support(np.array([1.0, 0.0])) == pytest.approx(7.0)
    assert not exact.is_subset_of(Box([-5.0, -2.0], [2.0, 2.0]))
    ring = FunctionSet(lambda x: 0.25 - ca.sumsqr(x), 2, name="outside_disc")  # concave row
    with pytest.raises(BalustradeError, match="outside_disc.support: row 0"):
        ring.support(np.array([1.0, 0.0]))
    assert disk(2.0).support(np.array([0.6, 0.8])) == pytest.approx(2.0, abs=1e-6)


def test_function_set_operations() -> None:
    D = disk(1.0, name="D")
    A = np.array([[2.0, 0.0], [1.0, 1.0]])
    AD = A @ D
    X = D.sample(300, 1, bounds=Box.symmetric(1.0, 2))
    assert X.shape == (300, 2) and np.all(np.sum(X**2, axis=1) <= 1)
    assert np.all(AD.contains_many(X @ A.T, tol=1e-9))
    assert not AD.contains(A @ np.array([1.01, 0.0]))
    assert np.all(D.translate([3.0, 0.0]).contains_many(X + [3.0, 0.0]))
    assert np.all(D.scale(-2.0).contains_many(-2 * X))
    assert not D.scale(0.5).contains([0.6, 0.0])
    assert np.isclose(D.support([3.0, 4.0]), 5.0, atol=1e-6)
    assert np.array_equal(D.contains_many(np.array([[0.0, 0.0], [2.0, 0.0]])), [True, False])
    assert isinstance(ca.evalf(AD.c(ca.DM([0.0, 0.0]))), ca.DM)


# -- sampling is uniform and reproducible ---------------------------------------------------------

def test_rng_seed_and_generator_are_reproducible() -> None:
    for S in (TRIANGLE, Box.symmetric(1.0, 2), Ellipsoid(np.eye(2))):
        a = S.sample(50, 7)
        b = S.sample(50, np.random.default_rng(7))
        assert np.array_equal(a, b)
        assert not np.array_equal(a, S.sample(50, 8))
        assert S.sample(0, 1).shape == (0, 2)


def test_ellipsoid_samples_are_uniform() -> None:
    for d in (1, 2, 3, 4):
        rng = np.random.default_rng(d)
        Q, _ = np.linalg.qr(rng.standard_normal((d, d)))
        P = Q @ np.diag(rng.uniform(0.5, 4.0, d)) @ Q.T
        E = Ellipsoid(P, center=rng.standard_normal(d))
        X = E.sample(20000, rng)
        inner = E.scale(0.5).translate(0.5 * E.center)  # the half-size ellipsoid, same centre
        frac = inner.contains_many(X).mean()
        p = 0.5**d
        assert abs(frac - p) < 4 * np.sqrt(p * (1 - p) / X.shape[0])
        assert np.allclose(X.mean(axis=0), E.center, atol=0.05)


@pytest.mark.parametrize("method", ["rejection", "hit_and_run"])
def test_polytope_samples_are_uniform(method: str) -> None:
    n = 4000
    X = TRIANGLE.sample(n, 3, method=method)
    assert np.all(TRIANGLE.contains_many(X))
    frac = np.mean(X[:, 0] <= 0.5)  # area fraction 3/4
    assert abs(frac - 0.75) < (4 if method == "rejection" else 8) * np.sqrt(0.75 * 0.25 / n)
    assert np.allclose(X.mean(axis=0), 1 / 3, atol=0.03)


def test_hit_and_run_matches_the_uniform_moments_of_a_box() -> None:
    B = Box([-1.0, -2.0], [1.0, 2.0])
    X = Polytope(B.H, B.h).sample(4000, 5, method="hit_and_run")
    assert np.allclose(X.var(axis=0) / [1 / 3, 4 / 3], 1.0, atol=0.06)
    inner = np.mean(np.max(np.abs(X) / [1.0, 2.0], axis=1) <= 0.5)  # area fraction 1/4
    assert abs(inner - 0.25) < 0.03


def test_thin_polytope_falls_back_to_hit_and_run() -> None:
    H = np.array([[1.0, -1.0], [-1.0, 1.0], [1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
    needle = Polytope(H, np.array([1e-5, 1e-5, 1.0, 1.0, 1.0, 1.0]), name="Needle")
    with pytest.raises(BalustradeError, match="Needle.*hit_and_run"):
        needle.sample(50, 0, method="rejection")
    X = needle.sample(1500, 0)  # auto: acceptance ~1e-5, hit-and-run with rounding
    assert np.all(needle.contains_many(X, tol=1e-12))
    assert np.allclose(X.mean(axis=0), 0.0, atol=0.1)
    assert np.allclose(X.std(axis=0), 1 / np.sqrt(3), rtol=0.1)


# -- SPEC §1.5 / §1.11 in use ------------------------------------------------------------------

def test_input_tightening_by_feedback_image_of_ellipsoid() -> None:
    """``U ⊖ K E = {A_u v <= b_u - [h_E(Kᵀ A_u,jᵀ)]_j}`` (SPEC §1.5) via ``K @ E``."""
    U = Box([-2.0], [3.0], name="U")
    P_E = np.array([[4.0, 1.0], [1.0, 2.0]])
    E = Ellipsoid(P_E, name="E")
    K = np.array([[-0.5, 0.8]])
    KE = K @ E
    T = U.tighten(KE)
    want = U.h - np.array([np.sqrt(a @ K @ np.linalg.solve(P_E, K.T @ a)) for a in U.H])
    assert np.allclose(T.h, want)
    assert T.name == "U⊖A·E"


def test_reachable_sets_of_the_linear_error_dynamics() -> None:
    """``E_i = ⊕_{j<i} (A+BK)^j W`` (SPEC §1.11) contains simulated errors and grows."""
    Acl = np.array([[0.9, 0.2], [-0.1, 0.7]])
    W = Box.symmetric(0.1, 2, name="W")
    E = [W]
    for _ in range(3):
        E.append(W.minkowski_sum(Acl @ E[-1]))  # E_{i+1} = W ⊕ Acl E_i
    rng = np.random.default_rng(0)
    e = np.zeros((500, 2))
    for Ei in E:
        e = e @ Acl.T + W.sample(500, rng)
        assert np.all(Ei.contains_many(e, tol=1e-9))
    for smaller, larger in zip(E[:-1], E[1:], strict=True):
        assert smaller.is_subset_of(larger) and not larger.is_subset_of(smaller)
    X = Box.symmetric(1.0, 2, name="X")
    tightened = [X.tighten(Ei) for Ei in E]
    assert all(isinstance(t, Box) for t in tightened)
    assert np.all(np.diff([t.ub[0] for t in tightened]) < 0)
