"""Error sets (SPEC §1.11): RPI by SDP and mRPI outer approximation, reachable-set tightenings,
tightening errors and the RPI check on bad input."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from balustrade.design.rpi import ellipsoidal_rpi
from balustrade.dsl.error_sets import (
    ErrorSet,
    is_rpi,
    minimal_rpi_outer,
    reachable_support,
    reachable_tightened_sets,
    tighten,
    tighten_by_feedback,
)
from balustrade.dsl.sets import Box, Ellipsoid
from balustrade.errors import EmptySetError
from balustrade.models.unstable2d import unstable2d, unstable2d_setup


@pytest.fixture(scope="module")
def design():
    system, s = unstable2d(), unstable2d_setup(10)
    return system, s, ellipsoidal_rpi(system.A, system.B, s.W, s.X, s.U)


def test_ellipsoidal_rpi_is_rpi_by_support_functions_and_sampling(design):
    system, s, es = design
    A_K = system.A + system.B @ es.K
    assert np.max(np.abs(np.linalg.eigvals(A_K))) < 1
    check = is_rpi(es.E, A_K, s.W)
    assert check.ok, check
    # independent sampling: boundary points of E and vertices/samples of W stay in E
    rng = np.random.default_rng(1)
    e = es.E.sample(3000, rng)
    e /= np.sqrt(np.einsum("ij,jk,ik->i", e, es.E.P, e))[:, None]
    w = np.vstack([s.W.vertices()[rng.integers(0, 4, 1500)], s.W.sample(1500, rng)])
    nxt = e @ A_K.T + w
    assert np.all(np.einsum("ij,jk,ik->i", nxt, es.E.P, nxt) <= 1 + 1e-7)
    # support functions along many directions: h_E(A_Kᵀa) + h_W(a) <= h_E(a)
    for a in rng.standard_normal((300, 2)):
        assert es.E.support(A_K.T @ a) + s.W.support(a) <= es.E.support(a) + 1e-9


def test_rpi_objective_is_the_documented_relative_tightening(design):
    system, s, es = design
    Pinv = np.linalg.inv(es.E.P)
    ox = sum((a @ Pinv @ a) / b ** 2 for a, b in zip(s.X.H, s.X.h))
    ou = sum((a @ es.K @ Pinv @ es.K.T @ a) / b ** 2 for a, b in zip(s.U.H, s.U.h))
    assert ox + ou == pytest.approx(es.info["objective"], rel=1e-4)


def test_non_rpi_set_is_detected_on_request(design):
    system, s, es = design
    A_K = system.A + system.B @ es.K
    small = es.E.scale(0.6, name="E_small")
    check = is_rpi(small, A_K, s.W)
    assert not check.ok and check.margin > 0
    # right set, wrong feedback
    assert not is_rpi(es.E, system.A, s.W).ok
    # polytopes: exact test
    assert not is_rpi(Box.symmetric([0.01, 0.01]), A_K, s.W).ok


def test_minimal_rpi_outer_approximation(design):
    system, s, es = design
    A_K = system.A + system.B @ es.K
    eps = 1e-3
    m = minimal_rpi_outer(A_K, s.W, eps=eps)
    F = m.polytope()
    assert is_rpi(F, A_K, s.W, tol=1e-9).ok
    # ε guarantee against the truncated sum F_s ⊆ F_∞: h_F(±e_j) − h_{F_s}(±e_j) <= ε
    for a in np.vstack([np.eye(2), -np.eye(2)]):
        h_Fs = m.support(a) * (1 - m.alpha)
        assert m.support(a) - h_Fs <= eps + 1e-12
        assert F.support(a) == pytest.approx(m.support(a), rel=1e-6)
    # trajectories of the error system from 0 stay in F
    rng = np.random.default_rng(0)
    e = np.zeros((200, 2))
    for _ in range(60):
        e = e @ A_K.T + s.W.sample(200, rng)
        assert np.all(F.contains_many(e, tol=1e-9))
    # the mRPI approximation is smaller than the ellipsoidal RPI set along the axes
    for a in np.eye(2):
        assert F.support(a) <= es.E.support(a) + 1e-9


def test_reachable_support_matches_vertex_enumeration(design):
    system, s, es = design
    A_K = system.A + system.B @ es.K
    H = np.vstack([s.X.H, np.array([[1.0, -2.0]])])
    sup = reachable_support(A_K, s.W, H, 4)
    Wv = s.W.vertices()
    for i in range(5):
        best = np.full(H.shape[0], -np.inf) if i else np.zeros(H.shape[0])
        for seq in itertools.product(range(len(Wv)), repeat=i):
            e = sum((np.linalg.matrix_power(A_K, j) @ Wv[k] for j, k in enumerate(seq)),
                    np.zeros(2))
            best = np.maximum(best, H @ e)
        np.testing.assert_allclose(sup[i], best, atol=1e-12)
    Us = reachable_tightened_sets(s.U, A_K, s.W, 4, K=es.K)
    assert Us[0].h == pytest.approx(s.U.h)
    assert np.all(np.diff([U.h[0] for U in Us]) < 0)


def test_tightenings_by_support_functions(design):
    system, s, es = design
    XE = tighten(s.X, es.E)
    Pinv = np.linalg.inv(es.E.P)
    np.testing.assert_allclose(XE.h, s.X.h - np.sqrt(np.einsum("ij,jk,ik->i", s.X.H, Pinv,
                                                                s.X.H)))
    UE = tighten_by_feedback(s.U, es.K, es.E)
    rng = np.random.default_rng(3)
    e = es.E.sample(2000, rng)
    assert np.max(np.abs(e @ es.K.T)) <= s.U.h[0] - UE.h[0] + 1e-12


def test_tightening_to_empty_names_the_set():
    X = Box.symmetric([0.1, 0.1], name="LaneX")
    big = Ellipsoid(np.eye(2) * 4.0, name="BigE")  # radius 0.5
    with pytest.raises(EmptySetError, match="LaneX"):
        tighten(X, big)
    U = Box.symmetric([0.1], name="SteerU")
    with pytest.raises(EmptySetError, match="SteerU"):
        tighten_by_feedback(U, np.array([[10.0, 0.0]]), big)
    with pytest.raises(EmptySetError, match="LaneX"):
        reachable_tightened_sets(X, 0.5 * np.eye(2), Box.symmetric([0.06, 0.06]), 5)


def test_user_given_error_set_for_nonlinear_systems():
    E = Ellipsoid(np.eye(2) * 100.0, name="E_user")
    es = ErrorSet(E, None, kappa_fn=lambda e: np.array([-np.tanh(e[0])]))
    assert es.kappa(np.array([0.1, 0.0]))[0] == pytest.approx(-np.tanh(0.1))
    assert es.tighten_state(Box.symmetric([1.0, 1.0])).h == pytest.approx(0.9 * np.ones(4))
    with pytest.raises(Exception, match="linear"):
        es.tighten_input(Box.symmetric([1.0]))


def test_rpi_sdp_is_a_synthesis_problem_with_lambda_as_a_parameter():
    """(5.14)/SPEC §1.11 is written in the synthesis language: one vertex LMI per vertex of
    W, λ a parameter of the compiled SDP (the line search re-solves without rebuilding)."""
    from balustrade.backends import compile_synthesis
    from balustrade.problems.rpi import rpi_sdp

    system, s = unstable2d(), unstable2d_setup(10)
    sdp = rpi_sdp(system.A, system.B, s.W, s.X, s.U)
    assert list(sdp.parameters) == ["lambda"]
    assert [k for k in sdp.constraints if k.startswith("vertex")] == \
        [f"vertex {v}" for v in range(len(s.W.vertices()))]
    compiled = compile_synthesis(sdp)
    assert compiled.cvxpy_problem.is_dpp()
    best = ellipsoidal_rpi(system.A, system.B, s.W, s.X, s.U)
    sol = compiled.solve({"lambda": best.info["lambda"]})
    assert sol.ok and sol.objective == pytest.approx(best.info["objective"], rel=1e-9)
    with pytest.raises(Exception, match=r"λ must lie in \(0, 1\)"):
        ellipsoidal_rpi(system.A, system.B, s.W, s.X, s.U, lambdas=[0.5, 1.0])


def test_rpi_line_search_never_takes_an_unverified_inaccurate_solve(monkeypatch):
    """(5.14): an ``optimal_inaccurate`` solve with a lower objective whose set is not RPI
    (here E shrunk 4×, checked below with an own trust-region-free test: the image of a
    boundary point leaves E) must not be chosen over the full-accuracy solves; the old line
    search took the lowest objective of any ``ok`` solve."""
    from dataclasses import replace

    from balustrade.backends import compile_synthesis
    from balustrade.backends.synthesis_cvxpy import CompiledSynthesis
    from balustrade.errors import BalustradeError
    from balustrade.problems.rpi import rpi_sdp

    system, s = unstable2d(), unstable2d_setup(10)
    real = CompiledSynthesis.solve

    def solve(self, params=None):
        sol = real(self, params)
        if sol.ok and abs(float(params["lambda"]) - 0.5) < 1e-12:
            vals = {**sol.values, "E": 0.25 * sol.values["E"], "Y": 0.25 * sol.values["Y"]}
            return replace(sol, status="optimal_inaccurate", objective=-1.0, values=vals)
        return sol

    monkeypatch.setattr(CompiledSynthesis, "solve", solve)
    bad = real(compile_synthesis(rpi_sdp(system.A, system.B, s.W, s.X, s.U)), {"lambda": 0.5})
    E_bad = 0.25 * bad["E"]
    K_bad = bad["Y"] @ np.linalg.inv(E_bad)
    P_bad = np.linalg.inv(E_bad)
    # own check: a point on ∂E mapped by A + BK plus a vertex of W lands outside E
    A_cl = system.A + system.B @ K_bad
    lam, V = np.linalg.eigh(P_bad)
    worst = max(float((A_cl @ e + w) @ P_bad @ (A_cl @ e + w))
                for t in np.linspace(0, 2 * np.pi, 400)
                for e in [V @ (np.array([np.cos(t), np.sin(t)]) / np.sqrt(lam))]
                for w in s.W.vertices())
    assert worst > 1.0
    err = ellipsoidal_rpi(system.A, system.B, s.W, s.X, s.U, lambdas=[0.5, 0.8])
    assert err.info["status"] == "optimal" and err.info["lambda"] == 0.8
    assert "refused" not in err.info      # the full-accuracy solve came first and passed
    with pytest.raises(BalustradeError, match="is RPI.*optimal_inaccurate"):
        ellipsoidal_rpi(system.A, system.B, s.W, s.X, s.U, lambdas=[0.5])


def test_rpi_of_an_ill_conditioned_design_is_rpi_by_an_own_check():
    """The bicycle linearization (§8.2, G = heading only): E_P of (5.14) has cond ≈ 1e6–1e8,
    and the best "optimal" solve's E = E_P⁻¹ missed A_K E ⊕ GW ⊆ E by 2.9e-6 (in eᵀPe units;
    other λ by 0.3). The returned set must pass an exact check done here by an S-lemma SDP
    per vertex of W: max_{eᵀPe ≤ 1} ‖A_K e + G w‖²_P ≤ 1."""
    import cvxpy as cp

    from balustrade.dsl.sets import Polytope
    from balustrade.examples.bicycle import G_HEADING, V_S, bicycle_sets
    from balustrade.models.bicycle import bicycle

    system, (X, U, W) = bicycle(), bicycle_sets()
    x_s = np.array([0.0, 0.0, V_S, 0.0])
    A, B = (np.asarray(M, dtype=float) for M in system.jacobians(x_s, np.zeros(2)))
    G = np.asarray(G_HEADING, dtype=float)
    err = ellipsoidal_rpi(A, B, W, Polytope(X.H, X.h - X.H @ x_s), U, G=G)
    P, A_K = err.E.P, A + B @ err.K
    n = A.shape[0]
    for w in W.vertices():
        g = G @ w
        t, lam = cp.Variable(), cp.Variable(nonneg=True)
        b = (A_K.T @ P @ g).reshape(n, 1)
        L = cp.bmat([[cp.reshape(t - g @ P @ g - lam, (1, 1)), -b.T],
                     [-b, lam * P - A_K.T @ P @ A_K]])
        cp.Problem(cp.Minimize(t), [(L + L.T) / 2 >> 0]).solve(solver="CLARABEL")
        assert t.value <= 1.0 + 1e-9, (w, t.value, err.info)
    assert err.info["inflation"] - 1.0 <= 1e-3


def test_is_rpi_warns_and_records_when_it_can_only_sample(design):
    """An ellipsoid with a non-polytope ``W`` gets no exact vertex trust-region check, only
    sampled directions and points: an ``ok`` is then no proof, so ``is_rpi`` warns
    (:class:`UnprovenCheckWarning`) and records ``proven=False`` with the reason in
    ``method``. A polytope ``W`` is proven silently, with a singular ``A_cl`` too (the exact
    check needs no inverse since audit E). Independent check of the singular case: ``A_cl``
    maps E onto a segment whose farthest point plus the largest ``w`` stays inside E
    (support functions along every row of a dense fan of directions)."""
    import warnings

    from balustrade.errors import UnprovenCheckWarning

    system, s, es = design
    A_sing = 0.3 * np.outer([1.0, 0.0], [1.0, 0.0])              # rank 1
    with warnings.catch_warnings():
        warnings.simplefilter("error", UnprovenCheckWarning)
        check = is_rpi(es.E, A_sing, s.W)
    assert check.ok and check.proven and "exact" in check.method
    for t in np.linspace(0, np.pi, 721):                            # it is RPI indeed
        a = np.array([np.cos(t), np.sin(t)])
        assert es.E.support(A_sing.T @ a) + s.W.support(a) <= es.E.support(a) + 1e-9
    ball = Ellipsoid(np.eye(2) / 1e-6, name="W_ball")             # W not a polytope
    with pytest.warns(UnprovenCheckWarning, match="not a polytope"):
        unproven = is_rpi(es.E, system.A + system.B @ es.K, ball)
    assert unproven.ok and not unproven.proven and "no proof" in unproven.method
    with warnings.catch_warnings():
        warnings.simplefilter("error", UnprovenCheckWarning)
        proven = is_rpi(es.E, system.A + system.B @ es.K, s.W)
        failed = is_rpi(es.E.scale(0.6, name="E_small"), A_sing * 10, s.W)
    assert proven.ok and proven.proven
    assert not failed.ok and failed.proven            # a counterexample is a proof
    assert es.info["rpi_proven"] is True


@pytest.mark.parametrize("n, miss", [(3, 1e-4), (4, 1e-4), (4, -1e-4)])
def test_is_rpi_is_exact_for_a_singular_closed_loop(n, miss):
    """Audit E (session 15): ``E`` the unit ball, ``A_cl = diag(a, …, a, 0)`` (singular) and
    ``W = [−h, h]ⁿ``: by hand, ``max_{||e||<=1} ||A_cl e + w||² = (a + h√(n−1))² + h²`` at
    ``w = h·1`` (``e`` along ``w``'s first ``n−1`` entries). With ``h`` chosen so that the
    maximum is ``1 + miss``, the margin is ``miss`` and a miss of 1e-4 is not RPI. Before, a
    singular ``A_cl`` got only the sampled checks, which under-estimate the maximum: for
    ``n = 4`` they reported −3.9e-5 and accepted the set."""
    a = 0.8
    # (a + h√(n−1))² + h² = 1 + miss: the positive root of n h² + 2a√(n−1) h + a² − 1 − miss
    r = np.sqrt(n - 1.0)
    h = (-2 * a * r + np.sqrt(4 * a * a * r * r - 4 * n * (a * a - 1 - miss))) / (2 * n)
    E = Ellipsoid(np.eye(n), name="ball")
    A_cl = np.diag([a] * (n - 1) + [0.0])
    check = is_rpi(E, A_cl, Box(-h * np.ones(n), h * np.ones(n), name="W"))
    assert check.margin == pytest.approx(miss, abs=1e-9)
    assert check.ok is (miss < 0)
    assert "exact" in check.method
