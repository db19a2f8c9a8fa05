"""Terminal-set enlargement of the homothetic-tube RAPSF (thesis Theorem 4.12, Remark 4.13,
SPEC §2.22) on the 2-state toy of ``test_rapsf.py`` with a short horizon (``N = 3``, where the
terminal set limits the admissible set): the enlarged set satisfies Assumption 4.11 at its
generators, contains the default set, keeps the closed loop safe, and makes states admissible
that the default terminal set does not."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from balustrade.backends import compile
from balustrade.backends.hull import extreme_points, hull_distances
from balustrade.control.rapsf import RAPSF
from balustrade.control.rapsf_enlarge import TerminalEnlargement
from balustrade.design.rapsf import check_assumption_4_11, contractive_polytope, robust_gain
from balustrade.design.rapsf_enlarge import (
    check_enlarged_terminal,
    enlarged_terminal_set,
    prune_terminal_set,
)
from balustrade.errors import BalustradeError, ShapeError
from balustrade.estimate import BoxUpdate
from balustrade.problems.rapsf import (
    TerminalSet,
    joint_constraints,
    model_matrices,
    rapsf_problem,
    s_constants,
)
from balustrade.problems.rapsf_enlarge import tube_pairs, zero_dilation_points

N = 3
STEPS = 25
GRID = np.array([[a, b] for a in np.linspace(-2, 2, 11) for b in np.linspace(-2, 2, 11)])


@pytest.fixture(scope="module")
def toy(rapsf_toy) -> SimpleNamespace:
    return rapsf_toy             # tests/conftest.py


@pytest.fixture(scope="module")
def run(toy) -> SimpleNamespace:
    """A closed loop with ``enlarge=True`` (CasADi target: generators as a parameter); at
    every step the same state is also solved with the default terminal set."""
    ctrl = RAPSF(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, toy.Theta0,
                 estimator=BoxUpdate(toy.sys, toy.W, toy.Theta0), target="exact",
                 enlarge=True)
    default = compile(rapsf_problem(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N), "exact")
    A, B = model_matrices(toy.sys, np.array([0.9, 0.2]))
    rng = np.random.default_rng(0)
    x, worst, pairs = np.array([0.9, 0.2]), -np.inf, []
    for k in range(STEPS):
        u_p = np.array([3.0 * np.sin(0.4 * k) + 1.5])          # aggressive: often unsafe
        u, info = ctrl.step(x, u_p)
        worst = max(worst, float(np.max(toy.F @ x + toy.G @ u - 1)))
        V = np.atleast_2d(ctrl.Theta.vertices())
        idx = np.arange(4) % len(V)
        ref = default.solve({"x0": x, "u_p": u_p, "theta": V[idx].T,
                             "s": s_constants(toy.X0, toy.sys, toy.K, V[idx])})
        pairs.append((ref.status == "optimal", "rapsf" not in info.uncertified
                      and info.fallback is None))
        x = A @ x + B @ u + 0.004 * rng.uniform(-1, 1, 2)
    return SimpleNamespace(ctrl=ctrl, worst=worst, pairs=pairs, terminal=ctrl.terminal_set,
                           vertices=np.atleast_2d(ctrl.Theta.vertices()))


# -- the set ----------------------------------------------------------------------------------
def test_enlarged_set_satisfies_assumption_4_11_at_its_generators(toy, run):
    ts = run.terminal
    assert ts.generators.shape[1] > 0
    report = check_enlarged_terminal(toy.sys, toy.X0, toy.W, toy.K, run.vertices, toy.F,
                                     toy.G, ts)
    assert report.ok, report.worst
    assert check_assumption_4_11(toy.sys, toy.X0, toy.W, toy.K, run.vertices, toy.F, toy.G,
                                 ts).worst == report.worst                # dispatches here
    # negative control: the generator farthest from the origin moved outward by 50 %
    V = ts.generators.copy()
    g = int(np.argmax(np.abs(V[:2]).sum(axis=0)))
    V[:2, g] *= 1.5
    bad = check_enlarged_terminal(toy.sys, toy.X0, toy.W, toy.K, run.vertices, toy.F, toy.G,
                                  TerminalSet.from_generators(V[:2], V[2]))
    assert not bad.ok and bad.worst > 1e-3
    assert int(np.argmax(bad.details["violations"])) == g


def test_enlarged_set_contains_the_default_set(toy, run):
    """The base set's generators (0, 0) and (0, 1) are in the hull, and every grid state
    admissible with the default terminal set stays admissible with the enlarged one."""
    ts = run.terminal
    base = np.array([[0.0, 0.0], [0.0, 0.0], [0.0, 1.0]])
    assert np.all(hull_distances(base, np.hstack([ts.generators, base])) <= 1e-9)
    counts = _grid_counts(toy, run)
    assert counts[(True, False)] == 0, counts


def test_admissible_set_grows(toy, run):
    """States infeasible with ``z_N = 0, α_N <= 1`` but feasible with the enlarged set
    (Theorem 4.12: the admissible set grows)."""
    counts = _grid_counts(toy, run)
    assert counts[(False, True)] >= 3, counts


def _grid_counts(toy, run) -> dict:
    if not hasattr(run, "counts"):
        pd = compile(rapsf_problem(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N,
                                   vertices=run.vertices), "fast-convex")
        pe = compile(rapsf_problem(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N,
                                   vertices=run.vertices, terminal=run.terminal),
                     "fast-convex")
        counts = {(a, b): 0 for a in (True, False) for b in (True, False)}
        for x in GRID:
            p = {"x0": x, "u_p": np.zeros(1)}
            counts[(pd.solve(p).status == "optimal", pe.solve(p).status == "optimal")] += 1
        run.counts = counts
    return run.counts


# -- the closed loop --------------------------------------------------------------------------
def test_closed_loop_is_safe_and_never_worse_than_default(run):
    assert run.worst <= 1e-6
    assert all(enl for dflt, enl in run.pairs if dflt), run.pairs   # default ok → enlarged ok
    assert len(run.ctrl._compiled) == 1                  # generators are a parameter
    assert run.ctrl.enlargement.recorded >= STEPS // 2


def test_numeric_hull_and_parameter_slot_agree(toy, run):
    """The numeric-generator form (``vertex_data="constants"``) and the parameter slot agree,
    the slot on CasADi (``exact``) and on the direct backend (``fast-convex``)."""
    ts = run.terminal
    num = compile(rapsf_problem(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N,
                                vertices=run.vertices, terminal=ts), "fast-convex")
    slots = [compile(rapsf_problem(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N,
                                   vertices=run.vertices, terminal=TerminalSet().slot(64)),
                     target) for target in ("exact", "fast-convex")]
    enl = TerminalEnlargement(2)
    enl.generators = ts.generators
    for x in (np.array([-1.4, 1.4]), np.array([0.5, 0.3])):
        p = {"x0": x, "u_p": np.array([2.0])}
        a = num.solve(p)
        assert a.status == "optimal"
        for slot in slots:
            b = slot.solve({**p, "terminal_generators": enl.padded()})
            assert b.status == "optimal"
            assert a["v"][:, 0] == pytest.approx(b["v"][:, 0], abs=1e-4)


def test_hull_over_an_h_representation_base(toy, run):
    """Generators over ``{H_T z + h_T α <= 1}`` (the perspective with a ``z'`` variable): the
    check passes, and the CasADi and convex targets agree on (4.5) with it."""
    small = TerminalSet(np.vstack([np.eye(2), -np.eye(2)]) / 0.05, np.full(4, 1.0))
    ts = enlarged_terminal_set(2, run.ctrl.enlargement.tubes[:6], base=small)
    assert ts.H_T is not None and ts.generators.shape[1] > 0
    assert check_enlarged_terminal(toy.sys, toy.X0, toy.W, toy.K, run.vertices, toy.F, toy.G,
                                   ts)
    ocp = rapsf_problem(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, vertices=run.vertices,
                        terminal=ts)
    p = {"x0": np.array([0.6, 0.4]), "u_p": np.array([2.5])}
    a, b = compile(ocp, "exact").solve(p), compile(ocp, "fast-convex").solve(p)
    assert a.status == b.status == "optimal"
    assert a["v"][:, 0] == pytest.approx(b["v"][:, 0], abs=1e-4)


def test_reset_clears_the_generators(toy):
    ctrl = RAPSF(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, toy.Theta0, enlarge=True,
                 target="fast-convex")
    u, info = ctrl.step(np.array([0.5, 0.1]), np.array([2.0]))
    assert info.values["n_generators"] > 0
    ctrl.reset()                         # back to Θ₀: the recorded tubes no longer count
    assert ctrl.terminal_set.generators.shape[1] == 0

    def failing(z, alpha):
        raise BalustradeError("a pruning LP failed")

    ctrl.enlargement.record = failing    # a failed bookkeeping step never fails the filter
    u, info = ctrl.step(np.array([0.5, 0.1]), np.array([2.0]))
    assert info.status == "enlarge_failed" and info.fallback is None
    assert ctrl.terminal_set.generators.shape[1] == 0


# -- generators and pruning -------------------------------------------------------------------
def test_pruning_removes_interior_generators():
    Z = np.array([[1.0, -1.0, 0.0, 0.0, 0.2, 1.0], [0.0, 0.0, 1.0, 0.0, 0.1, 0.0]])
    a = np.array([0.0, 0.0, 0.0, 0.5, 0.1, 0.0])           # 4: interior, 5: duplicate of 0
    ts = prune_terminal_set(TerminalSet.from_generators(Z, a))
    kept = {tuple(c) for c in ts.generators.T.round(12)}
    assert kept == {(1.0, 0.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 1.0, 0.0)}   # (0, .5) in base
    assert extreme_points(np.array([[0.0, 1.0, 2.0]])).tolist() == [True, False, True]


def test_extreme_points_match_qhull():
    """Screening + warm-started one-by-one LPs give the vertices of the convex hull."""
    P = np.random.default_rng(4).normal(size=(40, 3))
    P[5] = P[:4].mean(axis=0)                               # an interior point
    P[7] = P[3]                                             # a duplicate
    mask = extreme_points(P.T)
    expected = set(ConvexHull(P).vertices.tolist())
    assert set(np.flatnonzero(mask).tolist()) == expected - {7} or \
        set(np.flatnonzero(mask).tolist()) == expected - {3}
    assert not mask[5]
    many = np.random.default_rng(5).normal(size=(400, 3))      # above SCREEN_MIN: screened
    assert set(np.flatnonzero(extreme_points(many.T)).tolist()) == \
        set(ConvexHull(many).vertices.tolist())


def test_record_drops_candidates_inside_and_respects_capacity():
    z = np.array([[0.4, 0.2, 0.0], [0.0, 0.1, 0.0]])
    alpha = np.array([0.1, 0.5, 1.0])
    enl = TerminalEnlargement(2, X0_vertices=np.array([[1, 0], [0, 1], [-1, 0], [0, -1.0]]))
    assert enl.record(z, alpha) > 0
    before = enl.generators.copy()
    assert enl.record(0.5 * z, 0.5 * alpha) == 0            # inside the hull: nothing added
    assert np.array_equal(enl.generators, before)
    full = TerminalEnlargement(2, X0_vertices=np.array([[1, 0], [0, 1], [-1, 0], [0, -1.0]]),
                               capacity=2)
    assert full.record(z, alpha) == 0 and full.rejected == 1   # not even the last tube fits
    assert full.generators.shape[1] == 0
    # a tube starting far out: all 7 extreme points do not fit in 5, the suffix i >= 1 does
    far = np.array([[1.5, 0.2, 0.0], [0.0, 0.1, 0.0]])
    alpha = np.array([0.2, 0.5, 1.0])
    X = np.array([[1, 0], [0, 1], [-1, 0], [0, -1.0]])
    assert TerminalEnlargement(2, X0_vertices=X, capacity=7).record(far, alpha) == 7
    part = TerminalEnlargement(2, X0_vertices=X, capacity=5)
    assert part.record(far, alpha) == 4 and part.truncated == 1
    assert np.all(np.abs(part.generators[0]) <= 1.0)           # the i = 0 tube was dropped


def test_zero_dilation_points_are_tube_vertices():
    z = np.array([[0.4, 0.2], [0.0, 0.1]])
    alpha = np.array([0.1, 0.5])
    X = np.array([[1.0, 0.0], [0.0, 2.0]])
    P = zero_dilation_points(z, alpha, X)
    assert P.shape == (3, 4) and np.all(P[2] == 0)
    assert P[:2, 1] == pytest.approx([0.4, 0.2])           # z_0 + α_0 x^2
    offline = enlarged_terminal_set(2, [(z, alpha)], X0_vertices=X)
    assert np.all(hull_distances(P, np.hstack([offline.generators, np.zeros((3, 1))]))
                  <= 1e-9)


def test_bad_generator_shapes_raise_shape_error(toy):
    with pytest.raises(ShapeError, match="Z"):
        TerminalSet.from_generators(np.zeros(3), np.zeros(3))
    with pytest.raises(ShapeError, match="a"):
        TerminalSet.from_generators(np.zeros((2, 3)), np.zeros(2))
    with pytest.raises(BalustradeError, match=">= 0"):
        TerminalSet.from_generators(np.zeros((2, 1)), -np.ones(1))
    with pytest.raises(ShapeError, match="generators"):
        rapsf_problem(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, vertices=toy.V,
                      terminal=TerminalSet.from_generators(np.zeros((3, 1)), np.ones(1)))
    with pytest.raises(ShapeError, match="alpha"):
        tube_pairs(np.zeros((2, 4)), np.zeros(3))
    with pytest.raises(BalustradeError, match="dimension 3"):
        RAPSF(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, toy.Theta0,
              enlarge=TerminalEnlargement(3))


@pytest.mark.slow
def test_msd_three_masses_enlarged_closed_loop():
    """§4.7 chain, 3 masses, 30 steps with ``enlarge=True``: (x, u) ∈ 𝒵 at every step and the
    online set satisfies Assumption 4.11 at its generators for the final Θ."""
    from balustrade.models.msd import msd_chain, msd_performance, msd_setup

    sys_, st = msd_chain(3), msd_setup(3)
    V = st.Theta0.vertices()
    F, G = joint_constraints(st.X, st.U)
    K = robust_gain(sys_, V, contraction=0.95)
    X0 = contractive_polytope(sys_, K, V, st.W, F, G)
    rng = np.random.default_rng(5)
    theta = st.sample_theta(rng)
    ctrl = RAPSF(sys_, X0, F, G, st.W, K, st.N, st.Theta0,
                 estimator=BoxUpdate(sys_, st.W, st.Theta0), target="fast-convex",
                 enlarge=True)
    x = st.x0.copy()
    for k in range(30):
        u, info = ctrl.step(x, msd_performance(k, x, 3))
        assert np.all(F @ x + G @ u <= 1 + 1e-6), k
        x = sys_.step(x, u, theta, rng.uniform(-1e-3, 1e-3, 6))
    ts = ctrl.terminal_set
    assert ts.generators.shape[1] > 0 and not ctrl.enlargement.zero_dilation   # 216 vertices
    assert check_enlarged_terminal(sys_, X0, st.W, K, ctrl.Theta.vertices(), F, G, ts)
