"""Property tests of the set library (SPEC §1.3–1.5, §1.11) on random sets in 1–4 dimensions.

Sets are built from a hypothesis-drawn dimension and numpy seed, so that every example is
reproducible. Each property checks an operation against an independent computation:
samples against ``contains``, support functions against maximisers and vertices,
Pontryagin differences and Minkowski sums against pairwise sums of samples.
"""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from balustrade.dsl.sets import Box, Ellipsoid, Polytope, Set

TOL = 1e-7
PROFILE = settings(max_examples=30, deadline=None,
                   suppress_health_check=[HealthCheck.too_slow])

dims = st.integers(min_value=1, max_value=4)
seeds = st.integers(min_value=0, max_value=2**32 - 1)
kinds = st.sampled_from(["box", "polytope", "ellipsoid"])


# -- random sets ------------------------------------------------------------------------------

def rand_box(dim: int, rng: np.random.Generator, scale: float = 1.0,
             centered: bool = False) -> Box:
    half = scale * rng.uniform(0.2, 1.5, dim)
    c = np.zeros(dim) if centered else scale * rng.uniform(-1.0, 1.0, dim)
    return Box(c - half, c + half, name="RandBox")


def rand_polytope(dim: int, rng: np.random.Generator, scale: float = 1.0,
                  centered: bool = False) -> Polytope:
    """Bounded polytope containing the ball of radius ``0.5·scale`` around its centre; rows
    deliberately not normalised (SPEC §1.3)."""
    m = int(rng.integers(dim + 1, 2 * dim + 4))
    N = rng.standard_normal((m, dim))
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    H = np.vstack([N, np.eye(dim), -np.eye(dim)]) * rng.uniform(0.5, 3.0, (m + 2 * dim, 1))
    c = np.zeros(dim) if centered else scale * rng.uniform(-1.0, 1.0, dim)
    r = scale * np.concatenate([rng.uniform(0.5, 2.0, m), np.full(2 * dim, 2.5)])
    return Polytope(H, H @ c + np.linalg.norm(H, axis=1) * r, name="RandPoly")


def rand_ellipsoid(dim: int, rng: np.random.Generator, scale: float = 1.0,
                   centered: bool = False) -> Ellipsoid:
    Q, _ = np.linalg.qr(rng.standard_normal((dim, dim)))
    semi = scale * rng.uniform(0.3, 1.5, dim)
    P = Q @ np.diag(1.0 / semi**2) @ Q.T
    c = np.zeros(dim) if centered else scale * rng.uniform(-1.0, 1.0, dim)
    return Ellipsoid(0.5 * (P + P.T), c, name="RandEllipsoid")


MAKERS = {"box": rand_box, "polytope": rand_polytope, "ellipsoid": rand_ellipsoid}


def make(kind: str, dim: int, rng: np.random.Generator, **kw: object) -> Set:
    return MAKERS[kind](dim, rng, **kw)


def rand_dirs(dim: int, rng: np.random.Generator, k: int = 6) -> np.ndarray:
    A = rng.standard_normal((k, dim))
    return np.vstack([A, np.eye(dim), -np.eye(dim)])


def extreme_points(S: Set, rng: np.random.Generator) -> np.ndarray:
    """Points of ``S`` whose convex hull is (a dense subset of) ``S``'s boundary hull:
    vertices for polytopes, many boundary points for ellipsoids."""
    if isinstance(S, Polytope):
        return S.vertices()
    assert isinstance(S, Ellipsoid)
    u = rng.standard_normal((4000, S.dim))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return S.center + u @ S._root().T


def max_c(T: Set, X: np.ndarray) -> float:
    """``max_i max_j c_T(X_i)_j`` computed without the set's own vectorised code."""
    if isinstance(T, Polytope):
        return float(np.max(X @ T.H.T - T.h))
    assert isinstance(T, Ellipsoid)
    D = X - T.center
    return float(np.max(np.sum((D @ T.P) * D, axis=1) - 1.0))


# -- properties -------------------------------------------------------------------------------

@PROFILE
@given(kind=kinds, dim=dims, seed=seeds)
def test_samples_are_contained(kind: str, dim: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    S = make(kind, dim, rng)
    X = S.sample(300, rng)
    assert X.shape == (300, dim)
    assert np.all(S.contains_many(X))
    # the generic CasADi-mapped evaluation agrees with the closed-form vectorised one
    assert np.all(Set.contains_many(S, X))
    for x in X[:3]:
        assert S.contains(x)
    # samples spread over the set: not all equal, inside the bounding box
    assert np.ptp(X, axis=0).min() > 0
    bb = S.bounding_box()
    assert np.all(bb.contains_many(X, tol=1e-9))


@PROFILE
@given(kind=kinds, dim=dims, seed=seeds)
def test_support_bounds_samples_and_is_attained(kind: str, dim: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    S = make(kind, dim, rng)
    X = S.sample(200, rng)
    for a in rand_dirs(dim, rng):
        h = S.support(a)
        assert np.all(X @ a <= h + 1e-9 * (1 + abs(h)))
        if isinstance(S, Ellipsoid):
            # closed form attained at x* = q + P⁻¹a / sqrt(aᵀP⁻¹a), which lies in S
            Qa = np.linalg.solve(S.P, a)
            xs = S.center + Qa / np.sqrt(a @ Qa)
            assert S.contains(xs, tol=1e-9)
            assert np.isclose(a @ xs, h, rtol=1e-9, atol=1e-9)
        else:
            assert isinstance(S, Polytope)
            # LP (or closed form for boxes) vs vertex enumeration by qhull
            assert np.isclose(np.max(S.vertices() @ a), h, rtol=1e-7, atol=1e-7)
            if isinstance(S, Box):
                assert np.isclose(Polytope.support(S, a), h, rtol=1e-8, atol=1e-8)


@PROFILE
@given(kind_p=st.sampled_from(["box", "polytope"]), kind_b=kinds, dim=dims, seed=seeds)
def test_pontryagin_difference(kind_p: str, kind_b: str, dim: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    P = make(kind_p, dim, rng)
    B = make(kind_b, dim, rng, scale=0.05, centered=True)  # small enough to leave P⊖B ≠ ∅
    D = P.pontryagin_difference(B)
    assert D.H.shape == P.H.shape  # same rows, SPEC §1.5
    Y = D.sample(40, rng)
    Bs = B.sample(40, rng)
    if isinstance(B, Polytope):
        Bs = np.vstack([Bs, B.vertices()])
    sums = (Y[:, None, :] + Bs[None, :, :]).reshape(-1, dim)
    assert np.all(P.contains_many(sums, tol=TOL))
    assert D.is_subset_of(P)
    # exactness: along every row the tightening is the support of B (SPEC §1.4)
    for j, row in enumerate(P.H):
        assert np.isclose(P.h[j] - D.h[j], B.support(row), rtol=1e-9, atol=1e-9)


@PROFILE
@given(pair=st.sampled_from([("box", "box"), ("polytope", "polytope"), ("polytope", "box"),
                             ("ellipsoid", "ellipsoid"), ("polytope", "ellipsoid"),
                             ("ellipsoid", "box"), ("box", "ellipsoid")]),
       dim=dims, seed=seeds)
def test_minkowski_sum(pair: tuple[str, str], dim: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    if pair == ("polytope", "polytope"):
        dim = min(dim, 3)
    A = make(pair[0], dim, rng)
    B = make(pair[1], dim, rng, scale=0.5, centered=True)
    S = A.minkowski_sum(B)
    Xa, Xb = A.sample(200, rng), B.sample(200, rng)
    assert np.all(S.contains_many(Xa + Xb, tol=TOL))
    exact = "ellipsoid" not in pair
    for d in rand_dirs(dim, rng):
        want = A.support(d) + B.support(d)
        got = S.support(d)
        if exact:
            assert np.isclose(got, want, rtol=1e-6, atol=1e-6)
        else:  # outer approximations (documented)
            assert got >= want - 1e-7 * (1 + abs(want))
    assert A.is_subset_of(S)  # 0 ∈ B
    if isinstance(A, Box) and isinstance(B, Box):
        assert isinstance(S, Box)


@PROFILE
@given(kind=kinds, dim=dims, seed=seeds, square=st.booleans(), m=st.integers(1, 3))
def test_linear_map(kind: str, dim: int, seed: int, square: bool, m: int) -> None:
    rng = np.random.default_rng(seed)
    S = make(kind, dim, rng)
    if square:
        Q1, _ = np.linalg.qr(rng.standard_normal((dim, dim)))
        Q2, _ = np.linalg.qr(rng.standard_normal((dim, dim)))
        A = Q1 @ np.diag(rng.uniform(0.3, 3.0, dim)) @ Q2
    else:
        m = min(m, dim) if kind == "ellipsoid" else m  # ellipsoids need full row rank
        A = rng.standard_normal((m, dim))
    AS = A @ S
    assert AS.dim == A.shape[0]
    X = S.sample(200, rng)
    assert np.all(AS.contains_many(X @ A.T, tol=1e-6))
    for a in rand_dirs(A.shape[0], rng):
        want = S.support(A.T @ a)
        assert np.isclose(AS.support(a), want, rtol=1e-6, atol=1e-6)


@PROFILE
@given(kind_s=kinds, kind_t=st.sampled_from(["box", "polytope", "ellipsoid"]), dim=dims,
       seed=seeds)
def test_containment_agrees_with_extreme_points(kind_s: str, kind_t: str, dim: int,
                                                 seed: int) -> None:
    rng = np.random.default_rng(seed)
    S = make(kind_s, dim, rng, scale=0.6)
    T = make(kind_t, dim, rng, scale=1.4, centered=True)
    sub = S.is_subset_of(T)
    # c_T is convex, so its max over S is attained at extreme points of S
    points = extreme_points(S, rng)
    exact = isinstance(S, Polytope)
    if isinstance(S, Ellipsoid) and isinstance(T, Polytope):
        # the ellipsoid's maximizer of each facet normal a, c + P^-1 a / sqrt(a' P^-1 a): exact
        # witnesses (4000 sampled boundary points in 4-D fell 1.2e-2 short of the maximum)
        G = np.linalg.solve(S.P, T.H.T).T
        points = np.vstack([points, S.center + G / np.sqrt(np.sum(G * T.H, axis=1))[:, None]])
        exact = True
    worst = max_c(T, points)
    if sub:
        assert worst <= 1e-6
        assert np.all(T.contains_many(S.sample(200, rng), tol=1e-6))
    elif exact:
        assert worst > 1e-7  # vertices / facet maximizers are exact witnesses
    else:
        assert worst > -1e-3  # boundary points of an ellipsoid approximate the witness


@PROFILE
@given(kind=kinds, dim=dims, seed=seeds)
def test_containment_of_sums_differences_and_scalings(kind: str, dim: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    S = make(kind, dim, rng)
    small = rand_box(dim, rng, scale=0.1, centered=True)
    assert S.is_subset_of(S.minkowski_sum(small))
    c, _ = S.chebyshev_center()
    Sc = S.translate(-c)
    assert Sc.is_subset_of(Sc.scale(1.05))
    assert not Sc.scale(1.05).is_subset_of(Sc)
    assert S.is_subset_of(S)
    assert S.is_subset_of(S.bounding_box())
    if isinstance(S, Polytope):
        assert S.pontryagin_difference(small).is_subset_of(S)
        assert not S.is_subset_of(S.pontryagin_difference(small))


@PROFILE
@given(dim=st.integers(1, 3), seed=seeds)
def test_ellipsoid_in_ellipsoid_is_exact(dim: int, seed: int) -> None:
    """The trust-region value equals the brute-force max of c_T over S's boundary."""
    rng = np.random.default_rng(seed)
    S = rand_ellipsoid(dim, rng, scale=0.7)
    T = rand_ellipsoid(dim, rng, scale=1.2, centered=True)
    exact = T.max_quadratic_over(S)
    u = rng.standard_normal((20000, dim))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    brute = max_c(T, S.center + u @ S._root().T) + 1.0
    assert exact >= brute - 1e-9 * (1 + brute)
    assert exact <= brute * (1 + 2e-2) + 1e-9
    assert S.is_subset_of(T) == (exact <= 1.0 + 1e-7)


@PROFILE
@given(kind=kinds, dim=dims, seed=seeds, alpha=st.floats(-3.0, 3.0).filter(lambda a: abs(a) > .1))
def test_scale_and_translate(kind: str, dim: int, seed: int, alpha: float) -> None:
    rng = np.random.default_rng(seed)
    S = make(kind, dim, rng)
    v = rng.uniform(-2, 2, dim)
    X = S.sample(100, rng)
    assert np.all(S.scale(alpha).contains_many(alpha * X, tol=1e-7))
    assert np.all(S.translate(v).contains_many(X + v, tol=1e-7))
    for a in rand_dirs(dim, rng, 3):
        assert np.isclose(S.scale(alpha).support(a), S.support(alpha * a), rtol=1e-7, atol=1e-7)
        assert np.isclose(S.translate(v).support(a), S.support(a) + a @ v, rtol=1e-7,
                          atol=1e-7)


@PROFILE
@given(dim=dims, seed=seeds)
def test_polytope_geometry(dim: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    P = rand_polytope(dim, rng)
    V = P.vertices()
    assert np.all(P.contains_many(V, tol=1e-7))
    # every vertex makes at least dim rows active
    act = np.sum(np.abs(V @ P.H.T - P.h) <= 1e-7 * (1 + np.abs(P.h)), axis=1)
    assert np.all(act >= dim)
    bb = P.bounding_box()
    assert np.allclose(bb.lb, V.min(axis=0), atol=1e-7)
    assert np.allclose(bb.ub, V.max(axis=0), atol=1e-7)
    c, r = P.chebyshev_center()
    assert r >= 0.5 - 1e-7  # rand_polytope contains a ball of radius 0.5
    dist = (P.h - P.H @ c) / np.linalg.norm(P.H, axis=1)
    assert np.isclose(dist.min(), r, atol=1e-7)
