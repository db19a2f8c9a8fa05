"""Algorithm 4.1 with the Remark 4.6 shrinking-horizon variant as emitted C (issue #15 §4,
SPEC §2.21): after a failed (4.5) with ``k_inf <= N − 1`` and a stored plan, the C step
solves (4.5) with the horizon ``N − k_inf`` (one more emitted problem per horizon) and
applies its ``K x + v*_0``, else the stored plan, exactly as
:class:`balustrade.control.rapsf.RAPSF` with ``shrinking=True``.

The 2-state toy of ``tests/conftest.py`` with ``N = 5`` (five QPs in the module). Failures
are forced by inflating the support constants ``s_jr`` (SPEC §2.20) handed to both
controllers in chosen windows: the tube then grows by ``α_{i+1} >= 2.5 α_i + w̄``, so (4.5)
with the full horizon is infeasible while the shorter ones may not be; and by states
outside ``X`` (every horizon infeasible: stored plan, then backup)."""

from __future__ import annotations

import shutil
from collections import Counter

import numpy as np
import pytest

from balustrade.codegen import CRAPSF, build, build_executable, emit_rapsf
from balustrade.codegen.build import run_under_valgrind
from balustrade.codegen.emit_rapsf import EMITTABLE_TARGET, link_flags
from balustrade.control.rapsf import RAPSF
from balustrade.errors import CodegenError

N = 5
TOL = 1e-6
S_INFLATED = 2.5


@pytest.fixture(scope="module")
def toy(rapsf_toy):
    return rapsf_toy             # tests/conftest.py


def _controller(toy, **kw: object) -> RAPSF:
    return RAPSF(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, toy.Theta0,
                 target=EMITTABLE_TARGET, shrinking=True, **kw)


def test_deployment_spec_holds_every_shrunk_horizon(toy, tmp_path) -> None:
    """``deployment_spec`` of a shrinking RAPSF carries (4.5) for the horizons ``1 … N−1``
    (the objects the Python controller solves), and a spec missing one is refused before
    anything is written."""
    py = _controller(toy)
    spec = py.deployment_spec()
    assert sorted(spec.problems) == ["main"] + [f"shrunk{h}" for h in range(1, N)]
    for h in range(1, N):
        assert spec.problems[f"shrunk{h}"] is py._compiled[(h, spec.n_vertices)]
        assert spec.problems[f"shrunk{h}"].ocp.N == h
    del spec.problems["shrunk2"]
    with pytest.raises(CodegenError, match="horizon 2"):
        emit_rapsf(spec, "r", tmp_path)
    assert not list(tmp_path.iterdir())


@pytest.fixture(scope="module")
def emitted(toy, tmp_path_factory: pytest.TempPathFactory) -> dict:
    py = _controller(toy)
    out = tmp_path_factory.mktemp("rapsf_shrink_c")
    em = emit_rapsf(py, "rs", out)
    lib = build(out, em.name, werror=True, extra_flags=link_flags(em.libraries))
    return {"py": py, "emitted": em, "lib": lib}


def _same(py_out: tuple, c_out: tuple, where: object) -> None:
    (u1, i1), (u2, i2) = py_out, c_out
    assert np.max(np.abs(u1 - u2)) <= TOL, (where, u1, u2, i1.status, i2.status)
    assert i1.fallback == i2.fallback, (where, i1.fallback, i2.fallback, i1.status, i2.status)
    # the same solves uncertified (their status words differ: the C's BAL_NOT_CONVERGED is
    # the backend's "max_iterations" / "infeasible"), and ok exactly when ok
    assert set(i1.uncertified) == set(i2.uncertified), (where, i1.uncertified,
                                                        i2.uncertified)
    assert (i1.status == "ok") == (i2.status == "ok"), (where, i1.status, i2.status)
    assert set(i1.values) == set(i2.values), (where, i1.values, i2.values)
    for key, a in i1.values.items():
        assert abs(a - i2.values[key]) <= TOL * max(1.0, abs(a)), (where, key, a, i2.values)


@pytest.mark.slow
def test_c_equals_python_with_forced_failures(toy, emitted: dict) -> None:
    """A closed loop of the toy (true θ inside Θ₀, random |w| <= 0.004) with two windows of
    inflated ``s`` (near the origin: the shrunk horizons succeed; on a larger excursion:
    some fail, the stored plan is used) and then a state outside ``X``: the C and the
    Python controller give the same input within 1e-6, the same fallback, status,
    uncertified solves and ``k_inf``/``objective`` at every step, and every branch of
    Algorithm 4.1 with Remark 4.6 is visited."""
    py = emitted["py"]
    c = CRAPSF(emitted["lib"], host=py)
    assert c.shrinking
    py.reset()
    c.reset()
    s_true = py._s.copy()
    rng = np.random.default_rng(4)
    theta = np.array([1.2, 0.3])
    x, paths = np.array([0.05, 0.0]), Counter()
    for k in range(44):
        u_p = np.array([0.3 * np.sin(0.7 * k) if k < 22 else 3.0 * np.sin(0.7 * k) + 2.0])
        forced = 8 <= k < 8 + N or 30 <= k < 30 + N
        py._s = c.host._s = np.full_like(s_true, S_INFLATED) if forced else s_true
        out_py, out_c = py.step(x, u_p), c.step(x, u_p)
        _same(out_py, out_c, k)
        paths[out_py[1].fallback] += 1
        x = toy.sys.step(x, out_py[0], theta, rng.uniform(-0.004, 0.004, 2))
    py._s = c.host._s = s_true
    far = np.array([2.6, -2.4])                       # outside X = [−2, 2]²: all infeasible
    for k in range(N + 1):
        out_py, out_c = py.step(far, np.zeros(1)), c.step(far, np.zeros(1))
        _same(out_py, out_c, ("outside X", k))
        paths[out_py[1].fallback] += 1
    assert paths["shrunk_horizon"] >= 4 and paths["stored_plan"] >= 2, paths
    assert paths["backup"] >= 2 and paths[None] >= 20, paths


@pytest.mark.slow
def test_without_shrinking_the_c_uses_the_stored_plan(toy, tmp_path) -> None:
    """The same forced failures with ``shrinking=False``: the module has no shrunk problem
    (``SHRINKING 0``, empty X-macro) and C = Python take the stored plan, never
    ``shrunk_horizon``."""
    py = RAPSF(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, toy.Theta0,
               target=EMITTABLE_TARGET)
    em = emit_rapsf(py, "rn", tmp_path)
    assert sorted(em.manifest["problems"]) == ["main"] and not em.manifest["shrinking"]
    c = CRAPSF(build(tmp_path, em.name, werror=True, extra_flags=link_flags(em.libraries)),
               host=py)
    s_true, x, paths = py._s.copy(), np.array([0.05, 0.0]), Counter()
    for k in range(16):
        py._s = c.host._s = np.full_like(s_true, S_INFLATED) if 6 <= k < 6 + N else s_true
        u_p = np.array([0.3 * np.sin(0.7 * k)])
        out_py, out_c = py.step(x, u_p), c.step(x, u_p)
        _same(out_py, out_c, k)
        paths[out_py[1].fallback] += 1
        x = toy.sys.step(x, out_py[0], np.array([1.2, 0.3]))
    assert paths["stored_plan"] == N - 1 and paths["shrunk_horizon"] == 0, paths


VALGRIND_MAIN = r"""
#include <math.h>
#include <stdio.h>
#include "rs.h"
int main(void) {
  double x[2] = {0.05, 0.0}, up[1] = {0.2}, u[1], theta[rs_NQ * rs_NTH], s[rs_NXR * rs_NTH];
  int k, st, bad = 0, shrunk = 0;
  rs_work* wk = rs_alloc();
  if (!wk) return 2;
  for (k = 0; k < rs_NQ * rs_NTH; ++k) theta[k] = 0.5 + 0.25 * (k % 2);
  for (k = 0; k < rs_NXR * rs_NTH; ++k) s[k] = 0.9;
  rs_step(x, up, theta, s, 0, u, &st, wk);            /* stores a plan */
  bad += st != BAL_RAPSF_OK;
  for (k = 0; k < rs_NXR * rs_NTH; ++k) s[k] = 2.5;  /* (4.5) infeasible, shorter ones not */
  for (k = 0; k < 3; ++k) {
    rs_step(x, up, theta, s, 0, u, &st, wk);
    shrunk += st == BAL_RAPSF_SHRUNK_HORIZON;
    bad += !isfinite(u[0]);
  }
  x[0] = NAN;
  rs_step(x, up, theta, s, 0, u, &st, wk);
  bad += st != BAL_RAPSF_BAD_INPUT;
  rs_free(wk);
  printf("%d %d\n", bad, shrunk);
  return bad + (shrunk == 0);
}
"""


#: DAQP (the QP solver of "convex-qp", the casadi wheel's libdaqp.so) reads 8 bytes past
#: one of its own workspace blocks in ``update_LDL_remove`` while solving an infeasible QP
#: (here the full-horizon (4.5) with inflated ``s``, called from ``rs_main_solve``, the
#: same path without Remark 4.6). Only reads whose innermost frame is inside libdaqp are
#: suppressed; anything in balustrade's or CasADi's generated C still fails the test.
DAQP_SUPPRESSION = """{
   daqp_update_LDL_remove_reads_past_its_workspace
   Memcheck:Addr8
   obj:*libdaqp.so*
   ...
}
"""


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("valgrind") is None, reason="valgrind not installed")
def test_valgrind_clean_with_shrinking(emitted: dict) -> None:
    em = emitted["emitted"]
    (em.out_dir / "vg_main.c").write_text(VALGRIND_MAIN)
    supp = em.out_dir / "daqp.supp"
    supp.write_text(DAQP_SUPPRESSION)
    exe = build_executable(em.out_dir, "vg_main.c",
                           extra_flags=["-g", "-O1", *link_flags(em.libraries)])
    run = run_under_valgrind(str(exe), suppressions=supp, timeout=1200)
    assert run.returncode == 0, (run.stdout, run.stderr[-2000:])
    assert run.stdout.split() == ["0", "3"], run.stdout        # 3 shrunk-horizon steps
