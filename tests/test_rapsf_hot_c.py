"""Algorithm 4.1 emitted from the default RAPSF: (4.5) hot-started in C
(:mod:`balustrade.codegen.emit_rapsf_hot`, ``bal/rapsf_hot.c``; docs/deploy_c.md, "Session
15"). C = Python (the default target, its own engine of the newer library version and a
sparse interior-point fallback) on ≥ 1000 closed-loop states of the 3-mass chain of
``reproduce msd-adaptive``, the KKT acceptance rule computed in C, valgrind."""

from __future__ import annotations

import shutil
import subprocess

import numpy as np
import pytest

from balustrade.backends import daqp_engine
from balustrade.codegen import CRAPSF, build, build_executable, emit_rapsf
from balustrade.codegen.build import run_under_valgrind
from balustrade.codegen.emit_rapsf import link_flags
from balustrade.models.msd import msd_performance
from balustrade.reproduce import msd_adaptive

TOL = 1e-6


@pytest.fixture(scope="module")
def msd3() -> dict:
    return msd_adaptive.design(3)


def _emitted(d: dict, tmp, name: str = "rh") -> tuple[object, CRAPSF, object]:
    py = msd_adaptive.adaptive_controller(d)
    em = emit_rapsf(py, name, tmp)
    lib = build(tmp, name, werror=True, extra_flags=link_flags(em.libraries))
    return py, CRAPSF(lib, host=py), em


def _python_kkt(py, c: CRAPSF, x: np.ndarray, u_p: np.ndarray) -> tuple[float, np.ndarray]:
    """Python's :func:`~balustrade.backends.daqp_engine.kkt_residual` of the C's last point
    and multipliers on the lowered (4.5) Python computes for this step's data (the C's θ
    and ``s``; the QP with the shared rows or with every row, the one the C solved), and
    the point."""
    compiled = py.shared_rows_problem()[0] if c.qp_info()["shared"] else \
        py.deployment_spec().problems["main"]
    prog = compiled.program
    p = compiled.ocp.pack_parameters({
        "x0": x, "u_p": u_p, "theta": c._theta.reshape(c.nq, c.n_vertices, order="F"),
        "s": c._s.reshape(c.n_rows, c.n_vertices, order="F")})
    y, z = c.qp_point()
    A = prog.A.copy()
    if prog.A_param is not None:
        A.data = prog.A_data(p)
    m0 = sum(k for kind, k in prog.cones if kind == "zero")
    return daqp_engine.kkt_residual(compiled.engine.P, prog.q(p), A, prog.b(p), m0, y, z), y


def _independent(py, c: CRAPSF, x: np.ndarray, u_p: np.ndarray) -> float:
    """The C's last answer checked by Python's own code: the KKT residual
    (:func:`~balustrade.backends.daqp_engine.kkt_residual`) of the C's point and multipliers
    on the lowered (4.5) that Python computes for this step's data (the C's θ and ``s``;
    the QP with the shared rows or with every row, the one the C solved),
    and the C's ``v_0`` read through Python's variable layout: returns the larger of the
    residual and ``|u_C − (K x + v_0)|``."""
    kkt, y = _python_kkt(py, c, x, u_p)
    compiled = py.shared_rows_problem()[0] if c.qp_info()["shared"] else \
        py.deployment_spec().problems["main"]
    prog = compiled.program
    v = np.asarray(compiled.ocp.unpack_variables(y[:prog.n_w])["v"])[:, 0]
    return max(kkt, float(np.max(np.abs(c._u - (py.K @ x + v)))))


def _loops(d: dict, py, c: CRAPSF, seeds: range, steps: int) -> dict:
    """Closed loops driven by the Python default's inputs; at every state both controllers
    step (the C through its host's box update) and their inputs are compared."""
    system, st = d["system"], d["setup"]
    out = {"du": [], "status": [], "retried": 0, "states": 0, "kkt": [], "differ": [], "dobj": []}
    for seed in seeds:
        py.reset()
        c.reset()
        rng = np.random.default_rng(seed)
        theta = st.sample_theta(rng)
        if seed % 2:   # θ* at a vertex of Θ₀ and vertex disturbances
            theta = np.where(rng.random(theta.shape) < 0.5, st.Theta0.lb, st.Theta0.ub)
        x = st.x0.copy()
        for k in range(steps):
            u_p = msd_performance(k, x, d["n"])
            u, info = py.step(x, u_p)
            uc, cinfo = c.step(x, u_p)
            c.host._prev = (x, u)   # the applied input is Python's: its estimator sees it
            if info.fallback != cinfo.fallback:   # one of them solved, the other did not
                out["differ"].append((info, cinfo, _independent(py, c, x, u_p), uc))
            out["du"].append(float(np.max(np.abs(u - uc))))
            if info.fallback is None and cinfo.fallback is None:   # the same cost value
                a, b = info.values["objective"], cinfo.values["objective"]
                out["dobj"].append(abs(a - b) / (1.0 + abs(a)))
            out["status"].append((info.fallback, cinfo.fallback))
            q = c.qp_info()
            out["retried"] += q["retried"]
            if cinfo.fallback is None:
                out["kkt"].append(q["kkt"])
            out["states"] += 1
            w = rng.uniform(-st.W.ub, st.W.ub) if seed % 2 == 0 else \
                np.where(rng.random(2 * d["n"]) < 0.5, -st.W.ub, st.W.ub)
            x = system.step(x, u, theta, w)
    return out


@pytest.mark.slow
def test_c_equals_python_default_on_a_thousand_states(msd3, tmp_path) -> None:
    """1050 states (7 seeded loops of 150 steps; θ* uniform or at vertices, uniform or
    vertex disturbances): the C's inputs and objectives equal the Python default's within
    1e-6, the same steps fall back (except where only the C solved, checked below), and
    every used C answer passed the KKT check (<= 1e-8, in C)."""
    py, c, _ = _emitted(msd3, tmp_path)
    r = _loops(msd3, py, c, range(7), 150)
    assert r["states"] >= 1000
    same = [du for du, (a, b) in zip(r["du"], r["status"]) if a == b]
    assert max(same) <= TOL, max(same)
    assert max(r["dobj"]) <= TOL, max(r["dobj"])
    # where one solved and the other did not, the one that solved is the C with an answer
    # equal to the independent solve (Python's engine and its fallback stopped there)
    for info, cinfo, check, _ in r["differ"]:
        assert cinfo.fallback is None and info.uncertified["rapsf"] != "optimal", \
            (info.status, info.fallback, cinfo.status, cinfo.fallback)
        assert check <= daqp_engine.KKT_TOL
    assert len(r["differ"]) <= 0.01 * r["states"]
    assert max(r["kkt"]) <= daqp_engine.KKT_TOL
    print(f"\n{r['states']} states: max |du| {max(same):.2e} where both used a solve or "
          f"both fell back, {len(r['differ'])} steps only the C solved, "
          f"fallbacks {sum(a is not None for a, _ in r['status'])}, cold retries "
          f"{r['retried']}, worst KKT {max(r['kkt']):.2e}, objectives to "
          f"{max(r['dobj']):.1e} (relative)")


@pytest.mark.slow
def test_the_kkt_check_is_what_keeps_c_equal(msd3, tmp_path, monkeypatch) -> None:
    """One proximal iteration with a large weight leaves a biased point. With the KKT check
    the C does not use it (cold retry, then the stored plan/backup), so the steps it answers
    still equal Python's; with the check disabled (tolerance 1e30) the same C applies
    inputs off Python's by more than 1e-6 — the check, not luck, keeps them equal."""
    monkeypatch.setitem(daqp_engine.C_OPTIONS, "prox", 1.0)
    monkeypatch.setitem(daqp_engine.C_OPTIONS, "prox_iter", 1)
    py, c, _ = _emitted(msd3, tmp_path / "checked")
    r = _loops(msd3, py, c, range(1), 30)
    used = [du for du, (_, fb) in zip(r["du"], r["status"]) if fb is None]
    assert all(du <= TOL for du in used)
    assert sum(fb is not None for _, fb in r["status"]) > 0      # the check refused some

    real = daqp_engine.lowered_for_c

    def unchecked(compiled):
        low = real(compiled)
        return None if low is None else {**low, "kkt_tol": 1e30}
    monkeypatch.setattr("balustrade.codegen.emit_rapsf_hot.lowered_for_c", unchecked)
    py, c, _ = _emitted(msd3, tmp_path / "unchecked", "ru")
    r = _loops(msd3, py, c, range(1), 30)
    assert max(r["du"]) > TOL


VALGRIND_MAIN = r"""
#include <math.h>
#include <stdio.h>
#include "rh.h"
int main(void) {
  double x[rh_NX] = {0}, up[rh_NU] = {0}, theta[rh_NQ * rh_NTH], s[rh_NXR * rh_NTH], u[rh_NU];
  double info[5];
  int st, k, bad = 0;
  rh_work* wk = rh_alloc();
  if (!wk) return 3;
  for (k = 0; k < rh_NQ * rh_NTH; ++k) theta[k] = 0.15;
  for (k = 0; k < rh_NXR * rh_NTH; ++k) s[k] = 0.5;
  for (k = 0; k < 4; ++k) {
    x[0] = 0.2 * k;
    up[0] = 3.0;
    rh_step(x, up, theta, s, 0, u, &st, wk);
    rh_qp_info(wk, info);
    bad += !isfinite(u[0]);
  }
  theta[0] = 0.2; /* a new A(p): the working set activated again */
  rh_step(x, up, theta, s, 0, u, &st, wk);
  bad += !isfinite(u[0]);
  x[0] = 100.0; /* far outside X: (4.5) infeasible; hot, then cold, then the plan */
  rh_step(x, up, theta, s, 0, u, &st, wk);
  rh_qp_info(wk, info);
  bad += st != BAL_RAPSF_STORED_PLAN || info[3] != 1.0;
  x[0] = 0.2;
  rh_step(x, up, theta, s, 0, u, &st, wk); /* set up anew after the failure */
  bad += st != BAL_RAPSF_OK;
  rh_reset(wk);
  rh_step(x, up, theta, s, 1, u, &st, wk);
  bad += st != BAL_RAPSF_FALSIFIED;
  x[0] = NAN;
  rh_step(x, up, theta, s, 0, u, &st, wk);
  bad += st != BAL_RAPSF_BAD_INPUT;
  x[0] = 0.2;
  s[0] = NAN; /* a NaN s: bad input too */
  rh_step(x, up, theta, s, 0, u, &st, wk);
  bad += st != BAL_RAPSF_BAD_INPUT;
  rh_free(wk);
  printf("%d\n", bad);
  return bad;
}
"""


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("valgrind") is None, reason="valgrind not installed")
def test_valgrind_clean(msd3, tmp_path) -> None:
    """Set-up, hot solves, a changed A(p), a failed solve (hot, then cold, then the stored
    plan) and the set-up after it, reset, falsified and bad-input (NaN x, NaN s) steps,
    free: no invalid access, no definite leak."""
    _, _, em = _emitted(msd3, tmp_path)
    (tmp_path / "vg_main.c").write_text(VALGRIND_MAIN)
    exe = build_executable(tmp_path, "vg_main.c",
                           extra_flags=["-g", "-O1", *link_flags(em.libraries)])
    run = run_under_valgrind(str(exe), timeout=900)
    assert run.returncode == 0, run.stdout + run.stderr[-2000:]


@pytest.mark.slow
def test_rows_are_shared_only_when_the_data_repeat_them(msd3, tmp_path) -> None:
    """The C solves (4.5) with the shared rows exactly when
    :func:`~balustrade.problems.rapsf.rows_shared` holds for its data (checked in C):
    on the loop's data (a box Θ_k keeps the vertex order) it does; with one ``s_jr`` of a
    merged row changed it does not, and the C's answer (every row) equals Python's solve of
    (4.5) with every row at those data."""
    import ctypes

    from balustrade.codegen import cfiles
    from balustrade.problems.rapsf import rows_shared

    py, c, _ = _emitted(msd3, tmp_path)
    lib = ctypes.CDLL(str(tmp_path / "librh.so"))
    for entry in cfiles.ENTRY_POINTS["rapsf_hot"]:     # what <name>.h lists exists
        assert hasattr(lib, f"rh_{entry}"), entry
    st = msd3["setup"]
    x, u_p = st.x0 + 0.05, np.full(3, 1.0)
    c.step(x, u_p)
    _, rep, dep = py.shared_rows_problem()
    theta = c._theta.reshape(c.nq, c.n_vertices, order="F")
    s = c._s.reshape(c.n_rows, c.n_vertices, order="F").copy()
    assert c.qp_info()["shared"] and rows_shared(rep, dep, theta, s)
    r, j = np.argwhere(rep != np.arange(c.n_vertices)[None, :])[0]
    s[r, j] *= 1.01                                  # that row no longer a copy
    assert not rows_shared(rep, dep, theta, s)
    c._s[:] = s.reshape(-1, order="F")
    u, code = c.step_raw(x, u_p)
    assert code == c._OK and not c.qp_info()["shared"]
    sol = py.deployment_spec().problems["main"].solve(
        {"x0": x, "u_p": u_p, "theta": theta, "s": s})
    assert sol.status == "optimal"
    assert np.max(np.abs(u - (py.K @ x + np.asarray(sol.primal["v"])[:, 0]))) <= TOL


@pytest.mark.slow
def test_five_masses_are_refused_with_the_reason(tmp_path) -> None:
    """5 masses: the Python step's (4.5) with shared rows (1092 x 171) is on the hot-started
    engine, but (4.5) with every row (5452 x 471) is above its size limit (PIQP), and the C
    needs it for data that do not repeat the rows: refused, naming the size and
    ``convex-qp``, before anything is written."""
    from balustrade.errors import CodegenError

    ctrl = msd_adaptive.adaptive_controller(msd_adaptive.design(5))
    with pytest.raises(CodegenError, match=r"5452 x 471.*convex-qp"):
        emit_rapsf(ctrl, "r5", tmp_path)
    assert not list(tmp_path.iterdir())


@pytest.mark.slow
def test_non_finite_theta_or_s_is_bad_input(msd3, tmp_path) -> None:
    """A NaN ``s`` or a −∞ θ is bad input (review R1): no solve is reported, the input is
    the backup ``K x``, ``k_inf`` and the stored plan are kept (as for a NaN ``x``). Before,
    a NaN ``b_j`` read as "no bound" and the KKT check skipped that row: the step was OK."""
    py, c, _ = _emitted(msd3, tmp_path)
    x, u_p = msd3["setup"].x0 + 0.05, np.full(3, 1.0)
    c.step(x, u_p)
    assert c.qp_info()["flag"] == 1 and c.k_inf == 0
    theta, s = c._theta.copy(), c._s.copy()
    for name, bad in (("theta", -np.inf), ("s", np.nan)):
        c._theta[:], c._s[:] = theta, s
        getattr(c, f"_{name}")[:] = bad
        u, code = c.step_raw(x, u_p)
        assert code == c._BAD, (name, code)
        assert np.max(np.abs(u - py.K @ x)) <= 1e-12   # the backup, not the plan
        assert c.k_inf == 0
    c._theta[:], c._s[:] = theta, s          # the plan was kept: the next step solves again
    assert c.step_raw(x, u_p)[1] == c._OK


KKT_MAIN = r"""
#include <math.h>
#include <stdio.h>
#include "rh.c"
/* one solved step, then bal_hot_kkt at its point, and again with one inactive inequality
   row i scaled by 1e-9 and its bound moved so that the point misses it by 1 in the row's
   own unit (1e-9 unscaled) */
int main(void) {
  double x[rh_NX] = {0}, up[rh_NU] = {0}, theta[rh_NQ * rh_NTH], s[rh_NXR * rh_NTH], u[rh_NU];
  double before, after, ay = 0;
  int st, i, j, k, row = -1;
  bal_hot_qp* h;
  rh_work* wk = rh_alloc();
  if (!wk) return 3;
  for (k = 0; k < rh_NQ * rh_NTH; ++k) theta[k] = 0.15;
  for (k = 0; k < rh_NXR * rh_NTH; ++k) s[k] = 0.5;
  x[0] = 0.2;
  up[0] = 3.0;
  rh_step(x, up, theta, s, 0, u, &st, wk);
  if (st != BAL_RAPSF_OK) return 2;
  h = &wk->qps[wk->used];
  before = bal_hot_kkt(h);
  for (i = h->d->m0; i < h->d->m && row < 0; ++i) {
    if (!isfinite(h->b[i]) || h->lam[i] != 0.0) continue;
    for (k = 0; k < h->d->nnz; ++k) if (h->d->a_row[k] == i && h->aval[k] != 0.0) row = i;
  }
  if (row < 0) return 4;
  for (j = 0; j < h->d->n; ++j) {
    for (k = h->d->a_colptr[j]; k < h->d->a_colptr[j + 1]; ++k) {
      if (h->d->a_row[k] != row) continue;
      h->aval[k] *= 1e-9;
      ay += h->aval[k] * h->x[j];
    }
  }
  h->b[row] = ay - 1e-9;
  after = bal_hot_kkt(h);
  printf("%d %d %.17g %.17g %.17g\n", wk->used, row, before, after, h->b[row]);
  rh_free(wk);
  return 0;
}
"""


@pytest.mark.slow
def test_kkt_check_is_pythons_per_row_unit_rule(msd3, tmp_path) -> None:
    """The C's KKT residual is Python's ``kkt_residual`` (each row in its own unit
    ``n_i = max_j |A_ij|``; review R1): equal on the C's points of a closed loop, and on a
    crafted point that misses a row scaled by 1e-9 by 1 in that row's unit — 1e-9 unscaled,
    which the old rule (``/ (1 + |b_i|)``) accepted; Python and now the C refuse it."""
    import scipy.sparse as sp

    py, c, em = _emitted(msd3, tmp_path)
    st = msd3["setup"]
    solved, statuses = 0, []
    x, theta = st.x0.copy(), st.sample_theta(np.random.default_rng(0))
    for k in range(15):                        # C's residual = Python's on the same point
        u_p = msd_performance(k, x, msd3["n"])
        uc, code = c.step(x, u_p)
        if code.fallback is None:
            ck, (pk, _) = c.qp_info()["kkt"], _python_kkt(py, c, x, u_p)
            assert abs(ck - pk) <= 1e-12 + 1e-9 * pk, (k, ck, pk)
            solved += 1
        x = msd3["system"].step(x, uc, theta, np.zeros(2 * msd3["n"]))
    assert solved >= 10, statuses
    sub = tmp_path / "kkt"
    sub.mkdir()
    (sub / "kkt_main.c").write_text(KKT_MAIN)
    exe = build_executable(sub, "kkt_main.c",
                           extra_flags=[f"-I{tmp_path}", *link_flags(em.libraries)])
    run = subprocess.run([str(exe)], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stdout + run.stderr
    used, row, before, after, b_row = (float(v) for v in run.stdout.split())
    # the same point from the runtime (same code, same data, cold), checked by Python
    c.reset()
    c._theta[:] = 0.15
    c._s[:] = 0.5
    x, u_p = np.zeros(c.nx), np.zeros(c.nu)
    x[0], u_p[0] = 0.2, 3.0
    assert c.step_raw(x, u_p)[1] == c._OK and c.qp_info()["shared"] == bool(used)
    pk, y = _python_kkt(py, c, x, u_p)
    assert before <= daqp_engine.KKT_TOL and abs(before - pk) <= 1e-12 + 1e-9 * pk
    compiled = py.shared_rows_problem()[0] if used else py.deployment_spec().problems["main"]
    prog = compiled.program
    p = compiled.ocp.pack_parameters({
        "x0": x, "u_p": u_p, "theta": c._theta.reshape(c.nq, c.n_vertices, order="F"),
        "s": c._s.reshape(c.n_rows, c.n_vertices, order="F")})
    A = prog.A.copy()
    if prog.A_param is not None:
        A.data = prog.A_data(p)
    scale = np.ones(A.shape[0])
    scale[int(row)] = 1e-9
    A = sp.diags(scale) @ A
    b = prog.b(p).copy()
    b[int(row)] = b_row
    assert abs((A @ y)[int(row)] - b_row) == pytest.approx(1e-9, rel=1e-6)  # missed by 1e-9
    m0 = sum(k for kind, k in prog.cones if kind == "zero")
    _, z = c.qp_point()
    pk = daqp_engine.kkt_residual(compiled.engine.P, prog.q(p), A, b, m0, y, z)
    assert pk > daqp_engine.KKT_TOL and after == pytest.approx(pk, rel=1e-9)
