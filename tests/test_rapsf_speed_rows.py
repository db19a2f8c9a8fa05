"""Fewer rows in (4.5), exactly (issue #15, step time): a tube row of (4.5c) that does not
depend on some θ_k is the same row for vertices of a box Θ_k that differ only in θ_k, so it
is kept once (:func:`~balustrade.problems.rapsf.shared_rows`, checked on the data by
:func:`~balustrade.problems.rapsf.rows_shared`); and the factored form of (4.5c) moves the
vertex-independent part into variables of its own. Both must give the optimum of the full
problem."""

from __future__ import annotations

import numpy as np
import pytest

from balustrade.backends import compile
from balustrade.dsl.sets import Box, Polytope
from balustrade.estimate import BoxUpdate
from balustrade.models.msd import msd_performance
from balustrade.problems.rapsf import (
    row_dependence,
    rows_shared,
    shared_rows,
)


@pytest.fixture(scope="module")
def chain():
    from benchmarks.bench_rapsf import design
    return design(3)                      # 3 masses, contractive polytope 𝕏₀ (18 rows)


def _controller(d, **kw):
    from balustrade.control.rapsf import RAPSF
    st = d["setup"]
    return RAPSF(d["system"], d["X0"], d["F"], d["G"], st.W, d["K"], st.N, st.Theta0, **kw)


def test_position_rows_do_not_depend_on_the_springs(chain):
    dep = row_dependence(chain["system"], chain["X0"])
    HX = chain["X0"].H
    on_velocity = np.any(HX[:, 3:] != 0, axis=1)
    assert dep.shape == (HX.shape[0], 2)
    assert not np.any(dep[~on_velocity])              # a spring acts on velocities only
    assert np.all(np.any(dep[on_velocity], axis=1))
    V = chain["setup"].Theta0.vertices().T
    rep = shared_rows(dep, V)
    assert np.all(rep[~on_velocity] == 0)             # one row for all four vertices
    assert np.count_nonzero(rep == np.arange(4)) < 0.7 * rep.size


def test_rows_shared_is_false_for_data_that_do_not_repeat(chain):
    dep = row_dependence(chain["system"], chain["X0"])
    ctrl = _controller(chain, target="fast-convex")
    V = ctrl.vertices.T
    rep = shared_rows(dep, V)
    assert rows_shared(rep, dep, V, ctrl._s)
    skew = V.copy()
    skew[0, 1] += 1e-3                                  # vertex 1 differs in every θ
    assert not rows_shared(rep, dep, skew, ctrl._s)
    s = ctrl._s.copy()
    s[np.flatnonzero(rep[:, 1] == 0)[0], 1] += 1e-9
    assert not rows_shared(rep, dep, V, s)


def _states(d, count, seed=0):
    rng = np.random.default_rng(seed)
    X = d["setup"].X
    return [rng.uniform(0.6 * X.lb, 0.6 * X.ub) for _ in range(count)]


@pytest.mark.parametrize("factored", [False, True])
def test_reduced_problem_has_the_full_optimum(chain, factored):
    """Shared rows (and the factored form) against every row, on random states and a
    shrunk box: same status, objective and ``v₀`` (the applied input)."""
    ctrl = _controller(chain, target="fast-convex")
    ctrl._set_theta(Box([0.1, 0.12], [0.2, 0.13]))
    n_th = len(ctrl.vertices)
    rep = ctrl._shared_rows(n_th)
    assert rep is not None
    full = compile(ctrl._problem(ctrl.N, n_vertices=n_th, shared=None, factored=False),
                   "fast-convex")
    less = compile(ctrl._problem(ctrl.N, n_vertices=n_th, shared=rep, factored=factored),
                   "fast-convex")
    assert less.program.A.shape[0] < full.program.A.shape[0] or factored
    optimal = 0
    for k, x in enumerate(_states(chain, 12)):
        p = {"x0": x, "u_p": msd_performance(k, x, 3), "theta": ctrl.vertices.T,
             "s": ctrl._s}
        a, b = full.solve(p), less.solve(p)
        assert a.status == b.status
        if a.status == "optimal":
            optimal += 1
            assert abs(a.objective - b.objective) <= 1e-6 * (1 + abs(a.objective))
            np.testing.assert_allclose(np.asarray(b["v"])[:, 0], np.asarray(a["v"])[:, 0],
                                       atol=1e-6)
    assert optimal >= 6


def test_a_non_box_theta_uses_every_row(chain):
    """A Θ_k whose vertices share no coordinates (a rotated square inside Θ₀) fails
    :func:`rows_shared`: the controller solves the problem with every row, and its input
    equals that of the constant-vertex form."""
    c, r = np.array([0.15, 0.15]), 0.05
    Vt = c + r * np.array([[1, 0], [0, 1], [-1, 0], [0, -1.0]])
    H = np.array([[1, 1], [1, -1], [-1, 1], [-1, -1.0]])
    Theta = Polytope(H, H @ c + r, name="diamond")
    assert np.allclose(np.sort(Theta.vertices(), axis=0), np.sort(Vt, axis=0))
    par = _controller(chain, target="fast-convex")
    num = _controller(chain, target="fast-convex", vertex_data="constants")
    x = _states(chain, 1, seed=3)[0]
    u_p = msd_performance(2, x, 3)
    for ctrl in (par, num):
        ctrl.step(x, u_p)
        ctrl._set_theta(Theta)
    (u1, i1), (u2, i2) = par.step(x, u_p), num.step(x, u_p)
    assert i1.fallback is None and i2.fallback is None
    assert (par.N, 4, "all rows") in par._compiled       # not the shared problem
    np.testing.assert_allclose(u1, u2, atol=1e-6)


def test_closed_loop_equals_every_row(chain):
    """The 3-mass closed loop of the bench (box update, aggressive proposal) with shared
    rows and with every row: the same inputs along the loop."""
    from benchmarks.bench_rapsf import Loop
    st = chain["setup"]
    a = _controller(chain, target="fast-convex",
                    estimator=BoxUpdate(chain["system"], st.W, st.Theta0))
    b = _controller(chain, target="fast-convex",
                    estimator=BoxUpdate(chain["system"], st.W, st.Theta0))
    b._shared_rows = lambda n_th: None                      # every row, as before
    la, lb = Loop(chain, a.step, 25), Loop(chain, b.step, 25)
    for k in range(25):
        la(k)
        lb(k)
    assert list(a._compiled) == [(st.N, 4)] and la.fallbacks == lb.fallbacks == 0
    shared = a._compiled[(st.N, 4)].program.A.shape[0]
    every = b._compiled[(st.N, 4)].program.A.shape[0]
    assert shared < every
    np.testing.assert_allclose(np.array(la.applied), np.array(lb.applied), atol=1e-6)


def test_a_target_that_emits_c_keeps_every_row(chain):
    """The C step takes any vertex data, so the emittable target keeps every row in Python
    too (C = Python on the same problem); other targets share rows."""
    assert _controller(chain, target="convex-qp")._shared_rows(4) is None
    assert _controller(chain, target="exact")._shared_rows(4) is not None


def test_factored_rows_are_chosen_where_they_halve_the_nonzeros(chain):
    """3 masses (a sparse 𝕏₀): not factored (measured slower); 8 masses (the dense
    parallelotope of ``reproduce msd-adaptive``): factored (~11 instead of ~42 nonzeros per
    tube row). No compile here: the decision only."""
    from balustrade.problems.rapsf import factored_pays
    from balustrade.reproduce.msd_adaptive import design as design8

    keep3 = np.ones((chain["X0"].H.shape[0], 4), dtype=bool)
    assert not factored_pays(chain["system"], chain["X0"], chain["K"], keep3)
    d = design8(8)
    dep = row_dependence(d["system"], d["X0"])
    rep = shared_rows(dep, d["setup"].Theta0.vertices().T)
    keep8 = rep == np.arange(rep.shape[1])[None, :]
    assert 0.6 < keep8.mean() < 0.75                     # 2812 of 4096 rows kept
    assert factored_pays(d["system"], d["X0"], d["K"], keep8)


def test_the_emitted_target_is_the_one_that_keeps_every_row(chain):
    """``EMITTED_TARGETS`` names the target Algorithm 4.1's C is emitted from; a controller on
    a row-sharing target hands the C every row all the same (its deployment spec), since the
    C step cannot check that the vertex data repeat the shared rows."""
    from balustrade.codegen.emit_rapsf import EMITTABLE_TARGET
    from balustrade.control.rapsf import EMITTED_TARGETS
    assert EMITTABLE_TARGET in EMITTED_TARGETS
    ctl = _controller(chain, target="exact")
    rep = ctl._shared_rows(4)
    assert rep is not None

    def rows(ocp):
        return sum(b.rows for b in ocp.blocks)

    shared = rows(ctl._problem(ctl.N, n_vertices=4, shared=rep))
    ctl.step(np.zeros(ctl.n), np.zeros(ctl.K.shape[0]))     # caches the shared-row problem
    assert rows(ctl._compiled[(ctl.N, 4)].ocp) == shared
    emitted = rows(ctl.deployment_spec().problems["main"].ocp)
    every = rows(_controller(chain, target="convex-qp").deployment_spec().problems["main"].ocp)
    assert shared < emitted == every
