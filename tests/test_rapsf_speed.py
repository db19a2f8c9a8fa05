"""The fast step path of Algorithm 4.1 (issue #15 bench goal) gives the old path's answers:
the ``2q`` support LPs of the box/fixed-shape/hypercube updates in one HiGHS run
(:func:`balustrade.backends.lp.solve_lps_joint`) and ``s_jr`` of a new ``Θ_k`` from the
affine form of ``A_cl(θ)`` (SPEC §2.20) instead of
:func:`~balustrade.problems.rapsf.s_constants`."""

from __future__ import annotations

import numpy as np
import pytest

import balustrade.control.rapsf as rapsf_control
import balustrade.estimate.updates as updates
from balustrade.backends.lp import solve_lp, solve_lps, solve_lps_joint
from balustrade.backends.solution import Status
from balustrade.control.rapsf import RAPSF, _s_from_affine
from balustrade.dsl.sets import Box
from balustrade.estimate import BoxUpdate, HypercubeUpdate
from balustrade.problems.rapsf import model_matrices, s_constants

N = 8


@pytest.fixture(scope="module")
def toy(rapsf_toy):
    t = rapsf_toy                # tests/conftest.py
    return t.sys, t.Theta0, t.W, t.F, t.G, t.K, t.X0


def test_joint_lps_equal_single_lps_and_statuses():
    rng = np.random.default_rng(3)
    C = np.vstack([np.eye(3), -np.eye(3)])
    for _ in range(5):
        H, h = rng.normal(size=(16, 3)), rng.uniform(1.0, 2.0, 16)
        for maximize in (True, False):
            joint = solve_lps_joint(C, H, h, maximize=maximize)
            assert [r.status for r in joint] == [Status.OPTIMAL] * 6
            np.testing.assert_allclose([r.value for r in joint],
                                       [r.value for r in solve_lps(C, H, h, maximize)],
                                       rtol=0, atol=1e-10)
            for c, r in zip(C, joint, strict=True):  # each θ_i feasible and attains its value
                assert np.all(H @ r.x <= h + 1e-9)
                assert abs(c @ r.x - solve_lp(c, H, h, maximize).value) <= 1e-9
    box = np.vstack([np.eye(3), -np.eye(3)])
    empty = solve_lps_joint(C, box, np.array([1, 1, 1, -2, 0, 0.0]))
    assert len(empty) == 1 and empty[0].status is Status.INFEASIBLE and empty[0].x is None
    half = solve_lps_joint(C, np.eye(3)[:1], np.ones(1))      # unbounded rows: row by row
    assert [r.status for r in half] == [Status.OPTIMAL, Status.UNBOUNDED]
    free = solve_lps_joint(C, np.zeros((0, 3)), np.zeros(0))  # no rows: row by row
    assert [r.status for r in free] == [Status.UNBOUNDED]


def test_s_from_affine_equals_s_constants(toy):
    sys_, Theta0, W, F, G, K, X0 = toy
    ctrl = RAPSF(sys_, X0, F, G, W, K, N, Theta0)
    assert ctrl._s_affine is not None                         # the fast path is used here
    rng = np.random.default_rng(0)
    for _ in range(10):
        lo = rng.uniform(Theta0.lb, Theta0.ub)
        hi = rng.uniform(lo, Theta0.ub)
        V = Box(lo, hi).vertices()
        np.testing.assert_allclose(_s_from_affine(ctrl._s_affine, V),
                                   s_constants(X0, sys_, K, V, ctrl._X0_vertices),
                                   rtol=0, atol=1e-13)


def _loop(toy, estimator_cls, old: bool, monkeypatch, steps=25, target="fast-convex"):
    sys_, Theta0, W, F, G, K, X0 = toy
    with monkeypatch.context() as mp:
        if old:
            mp.setattr(updates, "solve_lps_joint", solve_lps)  # one warm-started run per row
            mp.setattr(updates, "_box_inside", lambda *a: False)  # LPs on every step
            mp.setattr(updates, "vertex_supports", lambda *a, **k: None)  # ... and no vertices
            mp.setattr(rapsf_control, "_s_from_lps",             # s_jr row by row
                       lambda *a, **kw: s_constants(*a))
        ctrl = RAPSF(sys_, X0, F, G, W, K, N, Theta0, estimator=estimator_cls(sys_, W, Theta0),
                     target=target)
        if old:
            ctrl._s_affine = None
            ctrl.reset()                                       # s of Θ₀ by s_constants
        rng = np.random.default_rng(4)
        theta = rng.uniform(Theta0.lb, Theta0.ub)
        A, B = model_matrices(sys_, theta)
        x, us, boxes, s = np.array([0.9, 0.2]), [], [], []
        for k in range(steps):
            u, info = ctrl.step(x, np.array([3.0 * np.sin(0.4 * k) + 1.5]))
            us.append(u)
            boxes.append(np.r_[ctrl.Theta.lb, ctrl.Theta.ub])
            s.append(ctrl._s.copy())
            x = A @ x + B @ u + 0.004 * rng.uniform(-1, 1, 2)
        no_lp = sum(r.lps == 0 for r in ctrl.estimator.history)
    return np.array(us), np.array(boxes), np.array(s), no_lp


@pytest.mark.parametrize("estimator_cls", [BoxUpdate, HypercubeUpdate])
def test_fast_path_equals_old_path_on_a_closed_loop(toy, estimator_cls, monkeypatch):
    toy_ = toy
    if estimator_cls is HypercubeUpdate:                       # Θ₀ must be a cube
        sys_, _, W, F, G, K, X0 = toy
        toy_ = (sys_, Box([0.5, 0.0], [1.0, 0.5], name="Theta0"), W, F, G, K, X0)
    u_new, box_new, s_new, no_lp_new = _loop(toy_, estimator_cls, False, monkeypatch, 50)
    u_old, box_old, s_old, no_lp_old = _loop(toy_, estimator_cls, True, monkeypatch, 50)
    assert len(np.unique(box_new, axis=0)) > 3                  # Θ_k does change
    assert no_lp_old == 0
    if estimator_cls is BoxUpdate:                              # steps with Θ_{k−1} ⊆ Δ_k
        assert no_lp_new > 0
    np.testing.assert_allclose(box_new, box_old, rtol=0, atol=1e-12)
    np.testing.assert_allclose(s_new, s_old, rtol=0, atol=1e-12)
    np.testing.assert_allclose(u_new, u_old, rtol=0, atol=1e-8)


def test_uninformative_transition_keeps_the_set_without_lps(toy):
    sys_, Theta0, W, F, G, K, X0 = toy
    est = BoxUpdate(sys_, W, Theta0)
    x, u = np.array([0.0, 0.0]), np.array([0.0])
    same = est.update(x, u, x)                      # x⁺ = 0 for every θ: Δ_k ⊇ Θ₀
    assert same is Theta0 and est.history[-1].lps == 0
    assert est.history[-1].status == "updated"
    A, B = model_matrices(sys_, np.array([1.0, 0.25]))
    x = np.array([0.9, 0.2])
    cut = est.update(x, u + 1.0, A @ x + B @ (u + 1.0))  # informative: a smaller box, from
    assert est.history[-1].lps == 0                     # the vertices of Θ₀ ∩ Δ₁ (q = 2)
    assert "vertices" in est.history[-1].reason
    assert np.prod(cut.ub - cut.lb) < np.prod(Theta0.ub - Theta0.lb)
    assert cut.contains(np.array([1.0, 0.25]), tol=1e-9)
    ctrl = RAPSF(sys_, X0, F, G, W, K, N, Theta0, estimator=BoxUpdate(sys_, W, Theta0),
                 target="fast-convex")
    ctrl.step(np.zeros(2), np.zeros(1))
    s_before = ctrl._s
    ctrl.step(np.zeros(2), np.zeros(1))                    # x⁺ = 0 again: nothing learned
    assert ctrl.Theta is Theta0 and ctrl._s is s_before     # no recomputation of s


def test_vertex_supports_equal_the_lps_and_fall_back_when_they_must(monkeypatch):
    """The box update's ``2q`` support LPs replaced by the vertices of ``Θ_{k−1} ∩ Δ_k``
    (:func:`~balustrade.estimate.updates.vertex_supports`, small ``q``): the same bounds
    on random transitions of the 3-mass chain (vertex disturbances included), θ* kept;
    ``None`` (the LPs decide) for an empty set and above the dimension limit; with the
    vertices switched off the update solves its ``2q`` LPs again."""
    from balustrade.estimate.nonfalsified import nonfalsified_set
    from balustrade.models.msd import msd_chain, msd_setup

    sys_, st = msd_chain(3), msd_setup(3)
    C = np.vstack([np.eye(2), -np.eye(2)])
    rng = np.random.default_rng(1)
    for trial in range(60):
        th = st.sample_theta(rng)
        box = Box(rng.uniform(st.Theta0.lb, th), rng.uniform(th, st.Theta0.ub))
        x, u = rng.uniform(-2, 2, 6), rng.uniform(-3.5, 3.5, 3)
        w = rng.uniform(-1e-3, 1e-3, 6)
        w = np.sign(w) * 1e-3 if trial % 3 == 0 else w
        both = nonfalsified_set(sys_, st.W, x, u, sys_.step(x, u, th, w)).intersect(box)
        v = updates.vertex_supports(C, both.H, both.h)
        lp = np.array([r.value for r in solve_lps_joint(C, both.H, both.h)])
        assert v is not None
        np.testing.assert_allclose(v, lp, rtol=0, atol=1e-11)
        assert np.all(C @ th <= v + 1e-12)                     # θ* inside the bounds
    empty = np.vstack([C, [[1.0, 0.0]]]), np.array([1.0, 1.0, 1.0, 1.0, -2.0])
    assert updates.vertex_supports(C, *empty) is None          # empty: the LP says so
    H4 = np.vstack([np.eye(4), -np.eye(4)])
    assert updates.vertex_supports(H4, H4, np.ones(8)) is None  # q = 4 > VERTEX_MAX_DIM
    est = BoxUpdate(sys_, st.W, st.Theta0)
    x, u = np.array([1.0, -1.0, 0.5, 0.3, -0.2, 0.1]), np.ones(3)
    xn = sys_.step(x, u, np.array([0.1, 0.2]))
    monkeypatch.setattr(updates, "VERTEX_MAX_DIM", 0)
    est.update(x, u, xn)
    assert est.history[-1].lps == 2 * sys_.q


def test_warm_start_follows_the_rule_of_the_emitted_c(toy):
    """``RAPSF(warm_start=True)``: (4.5) starts from the previous step's solution exactly
    when that step solved it optimally (``k_inf == 0``), else cold — the rule of the C
    (``BAL_RAPSF_WARM_START``); the inputs stay those of the cold controller (within the
    solver's accuracy); the default passes no start."""
    sys_, Theta0, W, F, G, K, X0 = toy
    ctrls = {w: RAPSF(sys_, X0, F, G, W, K, N, Theta0, target="convex-qp", warm_start=w)
             for w in (False, True)}
    starts: dict[bool, list] = {False: [], True: []}
    for w, ctrl in ctrls.items():
        ctrl._solve(np.zeros(2), np.zeros(1), N)                     # compile
        ctrl.reset()
        compiled = next(iter(ctrl._compiled.values()))
        solve = compiled.solve

        def spy(params, warm_start=None, _solve=solve, _w=w):
            starts[_w].append(warm_start)
            return _solve(params, warm_start=warm_start)
        compiled.solve = spy
    A, B = model_matrices(sys_, np.array([1.0, 0.25]))
    rng = np.random.default_rng(2)
    x, far = np.array([0.5, 0.1]), np.array([5.0, 5.0])              # far: (4.5) infeasible
    optimal, compared = [], 0
    for k in range(14):
        x_k = far if k == 6 else x
        u_p = np.array([3.0 * np.sin(0.5 * k)])
        (u_cold, i_cold), (u_warm, i_warm) = (c.step(x_k, u_p) for c in ctrls.values())
        optimal.append(i_warm.fallback is None)
        if i_cold.fallback is None and i_warm.fallback is None:
            compared += 1
            np.testing.assert_allclose(u_warm, u_cold, rtol=0, atol=1e-6)
        x = A @ x + B @ u_cold + 0.004 * rng.uniform(-1, 1, 2)
    assert all(s is None for s in starts[False])
    warm = [s is not None for s in starts[True]]
    assert len(warm) == 14 and not optimal[6] and compared >= 8
    assert warm == [False] + optimal[:-1]                # warm exactly after an optimal solve
    ctrls[True].reset()
    assert ctrls[True]._last is None


def test_s_from_l1_equals_s_constants_for_a_parallelotope():
    """The 8-mass design's 𝕏₀ is a parallelotope (closed-form supports ``‖aᵀT⁻¹diag(d)‖₁``):
    ``s_jr`` of a new ``Θ_k`` comes from one tensor product (``_s_l1``), the same numbers as
    :func:`~balustrade.problems.rapsf.s_constants`' support per row and vertex."""
    from balustrade.control.rapsf import _s_from_l1
    from balustrade.reproduce import msd_adaptive

    d = msd_adaptive.design(8)
    ctrl = msd_adaptive.adaptive_controller(d)
    assert ctrl._s_affine is None and ctrl._s_l1 is not None  # 16 states: no vertex list
    V0 = d["setup"].Theta0.vertices()
    np.testing.assert_allclose(ctrl._s, s_constants(d["X0"], d["system"], d["K"], V0),
                               rtol=0, atol=1e-13)
    rng = np.random.default_rng(1)
    lo = rng.uniform(d["setup"].Theta0.lb, d["setup"].Theta0.ub)
    V = Box(lo, rng.uniform(lo, d["setup"].Theta0.ub)).vertices()
    np.testing.assert_allclose(_s_from_l1(ctrl._s_l1, V),
                               s_constants(d["X0"], d["system"], d["K"], V),
                               rtol=0, atol=1e-13)


def test_split_benchmark_parts_and_baseline():
    """``benchmarks/rapsf_split.py`` (the per-part profile in docs/adaptive.md): the timers
    nest as documented (every part found by subtraction is >= 0, the QP solve is inside the
    step) and the step's inputs equal the rebuilt cvxpy transcription's."""
    from benchmarks.rapsf_split import PARTS, split

    r = split(3, 6)
    assert r["steps"] == 5 and r["fallbacks"] == 0
    assert 0 < r["mean"]["QP solve"] < r["mean"]["step"] and r["baseline_median"] > 0
    assert all(r["mean"][p] >= -1e-6 for p in PARTS), r["mean"]
    assert r["max_du_vs_baseline"] <= 1e-5


def _count_supports(monkeypatch) -> list:
    """Every call of ``Polytope.support`` (one LP per row: the old path of ``s_jr`` for a
    ``𝕏₀`` without enumerated vertices) appended to the returned list."""
    from balustrade.dsl.sets import Polytope

    calls: list = []
    original = Polytope.support

    def counted(self, a):
        calls.append(1)
        return original(self, a)

    monkeypatch.setattr(Polytope, "support", counted)
    return calls


def test_s_from_lps_equals_the_vertex_maximum_in_one_solver_run(toy, monkeypatch):
    """``s_jr`` of a new ``Θ_k`` for a polytope ``𝕏₀`` whose vertices are not enumerated
    (session 15: 480 ``support`` LPs per new ``Θ_k`` at 5 masses were most of a step):
    the exact maximum over the vertices of ``𝕏₀`` (independent: no LP) up to the LP
    tolerance, never below it (verified bounds), and no ``support`` call row by row."""
    from balustrade.control.rapsf import _s_affine, _s_from_lps

    sys_, Theta0, W, F, G, K, X0 = toy
    T = _s_affine(sys_, X0, K, X0.vertices())
    X0.verified_box()                                  # cached once per polytope, as in RAPSF
    calls = _count_supports(monkeypatch)
    rng = np.random.default_rng(1)
    for _ in range(5):
        lo = rng.uniform(Theta0.lb, Theta0.ub)
        V = Box(lo, rng.uniform(lo, Theta0.ub)).vertices()
        s, exact = _s_from_lps(X0, sys_, K, V), _s_from_affine(T, V)
        assert s.shape == exact.shape
        assert np.all(s >= exact - 1e-12) and np.all(s <= exact + 1e-9)
    assert calls == []


@pytest.mark.slow
def test_5_mass_steps_compute_s_without_an_lp_per_row(monkeypatch):
    """The 5-mass ``msd-adaptive`` design (a contractive polytope in 10 states, not
    enumerated): after the compiling step, steps whose ``Θ_k`` changes make no
    ``Polytope.support`` call (the old path made ``n_X · n_θ = 480`` per new ``Θ_k``), and
    ``s_jr`` equals :func:`s_constants` (row by row) to 1e-9."""
    from balustrade.models.msd import msd_performance
    from balustrade.reproduce import msd_adaptive

    d = msd_adaptive.design(5)
    assert d["X0"].dim > 6 and not hasattr(d["X0"], "support_l1_map")
    ctrl = msd_adaptive.adaptive_controller(d)
    s = d["setup"]
    rng = np.random.default_rng(0)
    theta, x = s.sample_theta(rng), s.x0.copy()
    u, _ = ctrl.step(x, np.zeros(d["n"]))                   # compiles (s_jr by s_constants)
    calls, changed = _count_supports(monkeypatch), 0
    for k in range(1, 6):
        x = d["system"].step(x, u, theta, rng.uniform(-s.W.ub, s.W.ub))
        before = ctrl.Theta
        u, _ = ctrl.step(x, msd_performance(k, x, d["n"]))
        changed += ctrl.Theta is not before
    assert changed >= 1 and calls == []
    assert ctrl._learned is not None and ctrl._learned.reused > 0   # rows without an LP
    monkeypatch.undo()
    np.testing.assert_allclose(ctrl._s, s_constants(d["X0"], d["system"], d["K"],
                                                    ctrl.vertices), rtol=0, atol=1e-9)


def test_learned_supports_equal_the_lps_and_reuse_vertices(monkeypatch):
    """:class:`~balustrade.control.rapsf_supports.LearnedSupports` on a random polytope in 8
    dimensions (no vertex enumeration there): the supports along 60 directions equal
    ``Polytope.support`` row by row (independent LPs) to 1e-8; directions moved by 1e-4 (a
    new ``Θ_k``) are answered mostly from the remembered vertices, no LP, with the same
    accuracy, while 60 new directions (whose best remembered vertex is mostly not optimal:
    the gap test sends them to LPs) are too."""
    from balustrade.control.rapsf_supports import LearnedSupports
    from balustrade.dsl.sets import Polytope

    rng = np.random.default_rng(7)
    H = rng.normal(size=(40, 8))
    P = Polytope(H, np.ones(40), name="P8")
    sup = LearnedSupports(P)
    D = rng.normal(size=(60, 8))
    moved = np.vstack([D + 1e-4 * rng.normal(size=D.shape), rng.normal(size=(60, 8))])
    for step, dirs in enumerate((D, moved)):
        got = sup(dirs)
        ref = np.array([P.support(d) for d in dirs])
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-8)
        if step == 0:
            assert sup.lps == 60 and sup.reused == 0 and len(sup.vertices) > 0
    assert sup.reused >= 30 and sup.lps < 150, (sup.reused, sup.lps)


def test_learned_supports_are_upper_bounds_when_the_vertex_is_nearly_optimal():
    """Review R1 (session 15): the value from a remembered vertex must be the verified upper
    bound, never the vertex's own value, which is below the support when the vertex is
    optimal only within the gap. The square ``[−1, 1]²`` remembers ``(−1, 1)`` (an LP along
    ``(−1, 1)``); along ``d = (ε, 1)`` the support is ``1 + ε`` at ``(1, 1)``, the
    remembered vertex gives ``1 − ε`` and passes the gap test (``2ε <= VERIFY_GAP·2``), so
    the answer must still be ``>= 1 + ε`` (exact here), not ``1 − ε``."""
    from balustrade.control.rapsf_supports import VERIFY_GAP, LearnedSupports
    from balustrade.dsl.sets import Polytope

    sq = Polytope(np.vstack([np.eye(2), -np.eye(2)]), np.ones(4), name="square")
    sup = LearnedSupports(sq)
    sup(np.array([[-1.0, 1.0]]))
    assert sup.lps == 1 and np.allclose(sup.vertices, [[-1.0, 1.0]])
    eps = 0.25 * VERIFY_GAP
    got = sup(np.array([[eps, 1.0]]))
    assert sup.reused == 1                       # answered by the remembered vertex
    assert got[0] >= 1.0 + eps - 1e-15, got[0] - (1.0 + eps)
