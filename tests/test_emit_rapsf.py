"""Algorithm 4.1 (the RAPSF, thesis Chapter 4, SPEC §2.21) as emitted C
(:mod:`balustrade.codegen.emit_rapsf`, :class:`balustrade.codegen.CRAPSF`), and the fast
robust-gain design for the 8-mass chain (:func:`balustrade.design.rapsf.robust_gain`).

The C tests build the 3-mass chain's QP (4.5) (1440 tube rows, ~0.8 MB of C, ~100 s to
compile under load): they are marked slow."""

from __future__ import annotations

import shutil
from collections import Counter

import numpy as np
import pytest

from balustrade.codegen import CRAPSF, build, build_executable, emit_rapsf
from balustrade.codegen.accelerate import registered
from balustrade.codegen.build import run_under_valgrind
from balustrade.codegen.emit_rapsf import EMITTABLE_TARGET, link_flags
from balustrade.control.rapsf import RAPSF
from balustrade.design.rapsf import (
    centre_lqr_gain,
    contractive_polytope,
    quadratic_contraction,
    robust_gain,
)
from balustrade.errors import BalustradeError, CodegenError
from balustrade.estimate import BoxUpdate
from balustrade.models.msd import msd_chain, msd_performance, msd_setup
from balustrade.problems.rapsf import closed_loop_matrices, joint_constraints

TOL = 1e-6


def _design(n: int = 3) -> dict:
    sys_, st = msd_chain(n), msd_setup(n)
    V = st.Theta0.vertices()
    F, G = joint_constraints(st.X, st.U)
    K = robust_gain(sys_, V, contraction=0.95)
    X0 = contractive_polytope(sys_, K, V, st.W, F, G)
    return {"sys": sys_, "st": st, "F": F, "G": G, "K": K, "X0": X0}


def _controller(d: dict, **kw: object) -> RAPSF:
    st = d["st"]
    kw.setdefault("target", EMITTABLE_TARGET)
    return RAPSF(d["sys"], d["X0"], d["F"], d["G"], st.W, d["K"], st.N, st.Theta0,
                 estimator=BoxUpdate(d["sys"], st.W, st.Theta0), **kw)


@pytest.fixture(scope="module")
def design3() -> dict:
    return _design(3)


# -- refusals (fast) ---------------------------------------------------------------------
def test_refuses_what_the_c_does_not_run(design3: dict, tmp_path) -> None:
    """A user's backup policy, the enlargement and a convex (non-parametric) target are
    refused with errors that say what to change, before anything is generated (Remark
    4.6, shrinking=True, is emitted: tests/test_rapsf_c_shrinking.py)."""
    with pytest.raises(CodegenError, match="backup"):
        emit_rapsf(_controller(design3, backup=lambda x, u_p, k: 0 * x[:3]), "r", tmp_path)
    with pytest.raises(CodegenError, match="enlarge"):  # its generators live in Python
        emit_rapsf(_controller(design3, enlarge=True), "r", tmp_path)
    with pytest.raises(BalustradeError, match="convex-qp"):
        emit_rapsf(_controller(design3, target="fast-convex"), "r", tmp_path)
    assert not list(tmp_path.iterdir())
    assert RAPSF in registered()                      # accelerate(rapsf) emits this step


# -- the robust gain of the 8-mass chain (fast) --------------------------------------------
def test_lqr_gain_is_certified_on_the_whole_box() -> None:
    """8 masses, 128 vertices: ``method="auto"`` returns the centre LQR gain (the LMI took
    > 400 s), and its certificate holds at random θ inside Θ₀ too (convexity argument of
    :func:`robust_gain`): ``A_cl(θ)ᵀ P A_cl(θ) ⪯ λ² P``."""
    sys_, st = msd_chain(8), msd_setup(8)
    V = st.Theta0.vertices()
    K = robust_gain(sys_, V, contraction=0.95)
    K_lqr, P = centre_lqr_gain(sys_, V)
    np.testing.assert_allclose(K, K_lqr)
    assert quadratic_contraction(sys_, K, P, V) <= 0.95
    rng = np.random.default_rng(0)
    thetas = rng.uniform(st.Theta0.lb, st.Theta0.ub, (50, 7))
    for Acl in closed_loop_matrices(sys_, K, thetas):
        gap = np.linalg.eigvalsh(0.95 ** 2 * P - Acl.T @ P @ Acl)
        assert gap.min() >= -1e-9


def test_lqr_certificate_refuses_a_too_strong_contraction() -> None:
    """The certificate is a real check: λ = 0.5 fails with ``method="lqr"``; ``"auto"``
    then falls back to the LMI (3 masses: 4 vertices use the LMI anyway)."""
    sys_, st = msd_chain(3), msd_setup(3)
    V = st.Theta0.vertices()
    with pytest.raises(BalustradeError, match="LQR"):
        robust_gain(sys_, V, contraction=0.5, method="lqr")
    with pytest.raises(BalustradeError, match="method"):
        robust_gain(sys_, V, method="riccati")
    K_lmi = robust_gain(sys_, V, contraction=0.95, method="lmi")
    np.testing.assert_allclose(robust_gain(sys_, V, contraction=0.95), K_lmi)


def test_batched_supports_screen_only_redundant_rows(design3: dict) -> None:
    """The speed-up of :func:`contractive_polytope` (dedup, bounding-box screen, one LP
    model): a row it reports ``<= 1`` is redundant by its own LP too, and a row above 1
    gets the LP's value — so the polytope gains the same rows as with one LP each."""
    from balustrade.design.rapsf import _supports

    X0 = design3["X0"]
    rng = np.random.default_rng(1)
    rows = [r for r in rng.normal(size=(60, 6)) * rng.uniform(0.05, 1.5, (60, 1))]
    _, values = _supports(X0, rows, 1e-9)
    exact = np.array([X0.support(r) for r in rows])
    screened = values <= 1 + 1e-9
    assert screened.any() and (~screened).any()
    assert np.all(exact[screened] <= 1 + 1e-7)
    np.testing.assert_allclose(values[~screened], exact[~screened], rtol=1e-7, atol=1e-9)


# -- the C step (slow: one ~100 s build) ---------------------------------------------------
@pytest.fixture(scope="module")
def emitted3(design3: dict, tmp_path_factory: pytest.TempPathFactory) -> dict:
    py = _controller(design3)
    out = tmp_path_factory.mktemp("rapsf_c")
    em = emit_rapsf(py, "rq", out)
    lib = build(out, em.name, werror=True, extra_flags=link_flags(em.libraries))
    return {"py": py, "emitted": em, "lib": lib}


def _same(py_out: tuple, c_out: tuple, where: object) -> None:
    (u1, i1), (u2, i2) = py_out, c_out
    assert np.max(np.abs(u1 - u2)) <= TOL, (where, u1, u2, i1.status, i2.status)
    assert i1.fallback == i2.fallback, (where, i1.fallback, i2.fallback, i1.status, i2.status)
    assert set(i1.values) == set(i2.values), (where, i1.values, i2.values)
    for key, a in i1.values.items():
        assert abs(a - i2.values[key]) <= TOL * max(1.0, abs(a)), (where, key, a, i2.values)


@pytest.mark.slow
def test_c_equals_python_along_a_closed_loop(design3: dict, emitted3: dict) -> None:
    """200 steps of the §4.7 chain (3 masses, the aggressive controller, the box update):
    the C and the Python controller (same target "convex-qp", same retry chain, no mirror
    mode) on the same states give the same input within 1e-6, the same fallback and the
    same ``k_inf``, ``n_vertices``, ``objective``."""
    d, st = design3, design3["st"]
    py = emitted3["py"]
    c = CRAPSF(emitted3["lib"], host=py)
    py.reset()
    rng = np.random.default_rng(3)
    theta = st.sample_theta(rng)
    x, paths = st.x0.copy(), Counter()
    for k in range(200):
        u_p = msd_performance(k, x, 3)
        out_py, out_c = py.step(x, u_p), c.step(x, u_p)
        _same(out_py, out_c, k)
        paths[out_py[1].fallback] += 1
        x = d["sys"].step(x, out_py[0], theta, rng.uniform(-1e-3, 1e-3, 6))
    assert paths[None] >= 100, paths                  # (4.5) solved on most steps
    np.testing.assert_allclose(c.host.Theta.vertices(), py.Theta.vertices())
    # then states outside X, where (4.5) is infeasible: the stored plan with the current
    # state's feedback for k_inf = 1 … N − 1, then the backup K x, in both
    far = np.full(6, 3.0)
    fallbacks = []
    for k in range(st.N + 1):
        u_p = msd_performance(200 + k, far, 3)
        py._prev = c.host._prev = None    # no Θ update from these states (else: falsified)
        out_py, out_c = py.step(far, u_p), c.step(far, u_p)
        _same(out_py, out_c, ("outside X", k))
        fallbacks.append(out_c[1].fallback)
    assert fallbacks == ["stored_plan"] * (st.N - 1) + ["backup"] * 2, fallbacks


@pytest.mark.slow
def test_c_equals_python_on_1000_closed_loop_states(design3: dict, emitted3: dict) -> None:
    """The must-show of issue #14 for bal/rapsf.c (audit C, session 14): 5 closed loops of
    200 steps (other parameters θ and disturbances than the loop above), 1000 states in
    all, inputs, fallbacks and values within 1e-6 (RAPSF keeps Θ and its plan from step to
    step, so its states are compared along loops, with fresh controllers per loop)."""
    d, st = design3, design3["st"]
    py = emitted3["py"]
    paths: Counter = Counter()
    for loop in range(5):
        c = CRAPSF(emitted3["lib"], host=py)
        py.reset()
        rng = np.random.default_rng(100 + loop)
        theta = st.sample_theta(rng)
        x = st.x0.copy()
        for k in range(200):
            u_p = msd_performance(k, x, 3)
            out_py, out_c = py.step(x, u_p), c.step(x, u_p)
            _same(out_py, out_c, (loop, k))
            paths[out_py[1].fallback] += 1
            x = d["sys"].step(x, out_py[0], theta, rng.uniform(-1e-3, 1e-3, 6))
    assert sum(paths.values()) == 1000 and paths[None] >= 500, paths


@pytest.mark.slow
def test_warm_started_c_equals_warm_started_python(design3: dict,
                                                   tmp_path_factory: pytest.TempPathFactory
                                                   ) -> None:
    """``RAPSF(warm_start=True)``: (4.5) starts from the previous step's solution after a
    converged solve, in C (``<name>_WARM_START``) as in Python; 150 steps of the closed loop
    give the same inputs, fallbacks and values (one more ~100 s build)."""
    d, st = design3, design3["st"]
    py = _controller(d, warm_start=True)
    out = tmp_path_factory.mktemp("rapsf_c_warm")
    em = emit_rapsf(py, "rw", out)
    assert em.manifest["warm_start"] is True
    assert "#define rw_WARM_START 1" in (out / "rw_config.h").read_text()
    c = CRAPSF(build(out, em.name, werror=True, extra_flags=link_flags(em.libraries)),
               host=py)
    py.reset()
    rng = np.random.default_rng(3)
    theta = st.sample_theta(rng)
    x, paths = st.x0.copy(), Counter()
    for k in range(150):
        u_p = msd_performance(k, x, 3)
        out_py, out_c = py.step(x, u_p), c.step(x, u_p)
        _same(out_py, out_c, k)
        paths[out_py[1].fallback] += 1
        x = d["sys"].step(x, out_py[0], theta, rng.uniform(-1e-3, 1e-3, 6))
    assert paths[None] >= 100, paths


@pytest.mark.slow
def test_bad_input_and_falsified_model(design3: dict, emitted3: dict) -> None:
    """A NaN state: nothing solved, the backup ``K x`` with NaN read as 0, status
    ``"non_finite_state"`` in both; a falsified model (the estimator excluded every θ):
    ``"model_falsified"`` and the backup in both."""
    py = emitted3["py"]
    c = CRAPSF(emitted3["lib"], host=py)
    py.reset()
    x = np.array([np.nan, 0.1, 0.0, 0.2, 0.0, 0.0])
    out_py, out_c = py.step(x, np.zeros(3)), c.step(x, np.zeros(3))
    _same(out_py, out_c, "nan")
    assert out_c[1].status == out_py[1].status == "non_finite_state"
    np.testing.assert_allclose(out_c[0], design3["K"] @ np.nan_to_num(x))
    py.falsified = c.host.falsified = True
    x = np.array([0.1, 0.0, 0.0, 0.0, 0.0, 0.0])
    out_py, out_c = py.step(x, np.ones(3)), c.step(x, np.ones(3))
    _same(out_py, out_c, "falsified")
    assert out_c[1].status == "model_falsified" and out_c[1].fallback == "backup"
    # a non-finite θ or s passed to the C step is bad input too (review R1, session 15)
    c.step(x, np.ones(3))
    theta, s = c._theta.copy(), c._s.copy()
    for name, bad in (("theta", -np.inf), ("s", np.nan)):
        c._theta[:], c._s[:] = theta, s
        getattr(c, f"_{name}")[:] = bad
        u, code = c.step_raw(x, np.ones(3))
        assert code == c._BAD, (name, code)
        np.testing.assert_allclose(u, design3["K"] @ x, atol=1e-12)
    py.reset()


VALGRIND_MAIN = r"""
#include <math.h>
#include <stdio.h>
#include "rq.h"
int main(void) {
  double x[6] = {0}, up[3] = {2.0, 0.0, 0.0}, u[3], theta[rq_NQ * rq_NTH], s[rq_NXR * rq_NTH];
  int k, st, bad = 0;
  rq_work* wk = rq_alloc();
  if (!wk) return 2;
  for (k = 0; k < rq_NQ * rq_NTH; ++k) theta[k] = 0.15;
  for (k = 0; k < rq_NXR * rq_NTH; ++k) s[k] = 0.9;
  for (k = 0; k < 3; ++k) {
    x[0] = 0.3 * k;
    rq_step(x, up, theta, s, 0, u, &st, wk);
    bad += !isfinite(u[0]);
  }
  x[0] = NAN;
  rq_step(x, up, theta, s, 0, u, &st, wk);
  bad += st != BAL_RAPSF_BAD_INPUT;
  rq_free(wk);
  printf("%d\n", bad);
  return bad;
}
"""


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("valgrind") is None, reason="valgrind not installed")
def test_valgrind_clean(emitted3: dict) -> None:
    em = emitted3["emitted"]
    (em.out_dir / "vg_main.c").write_text(VALGRIND_MAIN)
    exe = build_executable(em.out_dir, "vg_main.c",
                           extra_flags=["-g", "-O1", *link_flags(em.libraries)])
    run = run_under_valgrind(str(exe), timeout=1200)
    assert run.returncode == 0, run.stderr[-2000:]
