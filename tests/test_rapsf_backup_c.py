"""A user's backup policy ``π_Cf`` in Algorithm 4.1 (issue #15 §4, SPEC §2.21) and in its
emitted C step: an affine law ``(K_b, k_b)`` or a ``casadi.Function`` of ``x`` runs in the C
exactly where :class:`balustrade.control.rapsf.RAPSF` applies it (``k_inf > N − 1``, a
falsified model, a non-finite state); a Python callable runs in Python and is refused by
the emitter, naming ``backup``.

The 2-state toy of ``tests/conftest.py`` with ``N = 3`` (one QP, a few seconds to build).
Failures are forced as in ``tests/test_rapsf_c_shrinking.py``: inflated support constants
``s_jr`` handed to both controllers (the stored plan, then the backup), states outside ``X``,
a NaN state and a falsified model."""

from __future__ import annotations

import shutil
from collections import Counter

import casadi as ca
import numpy as np
import pytest

from balustrade.codegen import CRAPSF, build, build_executable, emit_rapsf
from balustrade.codegen.build import run_under_valgrind
from balustrade.codegen.emit_rapsf import EMITTABLE_TARGET, link_flags
from balustrade.control.rapsf import RAPSF
from balustrade.control.rapsf_backup import AffineBackup, FunctionBackup
from balustrade.errors import BalustradeError, CodegenError, ShapeError

N = 3
TOL = 1e-6
K_B, K_B0 = np.array([[-0.5, -1.0]]), np.array([0.1])
S_INFLATED = 30.0                                  # α_{i+1} >= 30 α_i + w̄: α_N > 1
FAR = np.array([2.6, -2.4])                       # outside X = [−2, 2]²: (4.5) infeasible


@pytest.fixture(scope="module")
def toy(rapsf_toy):
    return rapsf_toy             # tests/conftest.py


def _saturated(kind: str = "SX") -> ca.Function:
    """A nonlinear backup ``u = 3 tanh((−0.8 x₁ − 1.2 x₂)/3)`` (not affine: the C must run
    the function itself)."""
    x = (ca.SX if kind == "SX" else ca.MX).sym("x", 2)
    return ca.Function("sat", [x], [3.0 * ca.tanh((-0.8 * x[0] - 1.2 * x[1]) / 3.0)])


def _law(x: np.ndarray, kind: str) -> np.ndarray:
    x = np.where(np.isfinite(x), x, 0.0)
    if kind == "affine":
        return K_B @ x + K_B0
    return np.array([3.0 * np.tanh((-0.8 * x[0] - 1.2 * x[1]) / 3.0)])


def _controller(toy, backup: object, **kw: object) -> RAPSF:
    return RAPSF(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, toy.Theta0,
                 target=kw.pop("target", EMITTABLE_TARGET), backup=backup, **kw)


# -- Python: the spellings and bad input (fast) ----------------------------------------------
@pytest.mark.parametrize("backup,kind", [((K_B, K_B0), "affine"),
                                         (AffineBackup(K_B, K_B0), "affine"),
                                         (_saturated("SX"), "function"),
                                         (_saturated("MX"), "function")])
def test_backup_spellings_in_python(toy, backup: object, kind: str) -> None:
    """Outside ``X`` with no stored plan (``k_inf = N − 1``) and at a NaN state the step
    applies the user's law (NaN entries as 0), not ``K x``; the law is kept for the C."""
    py = _controller(toy, backup, target="fast-convex")
    assert isinstance(py.backup_law, AffineBackup if kind == "affine" else FunctionBackup)
    assert not py.default_backup
    for x, status in ((FAR, None), (np.array([np.nan, 0.5]), "non_finite_state")):
        u, info = py.step(x, np.zeros(1))
        assert info.fallback == "backup", info
        assert status is None or info.status == status
        np.testing.assert_allclose(u, _law(x, kind), atol=1e-12)
        assert abs(u[0] - (toy.K @ np.where(np.isfinite(x), x, 0.0))[0]) > 1e-3
    callable_py = _controller(toy, lambda x, u_p, k: np.array([0.25]), target="fast-convex")
    assert callable_py.backup_law is None
    assert callable_py.step(FAR, np.zeros(1))[0][0] == 0.25


def test_bad_backup_input_names_the_argument(toy) -> None:
    with pytest.raises(ShapeError, match=r"backup K_b.*\(1, 2\).*\(2, 2\)"):
        _controller(toy, (np.eye(2), K_B0))
    with pytest.raises(ShapeError, match="backup k_b"):
        _controller(toy, (K_B, np.ones(2)))
    with pytest.raises(BalustradeError, match=r"backup.*pair \(K_b, k_b\)"):
        _controller(toy, (K_B, K_B0, 1.0))
    x, y = ca.SX.sym("x", 2), ca.SX.sym("y", 1)
    with pytest.raises(BalustradeError, match="backup.*one input"):
        _controller(toy, ca.Function("f2", [x, y], [x[0] + y]))
    with pytest.raises(ShapeError, match=r"backup.*input x.*\(2, 1\).*\(3, 1\)"):
        _controller(toy, ca.Function("f3", [ca.SX.sym("z", 3)], [1.0]))
    with pytest.raises(ShapeError, match=r"backup.*output u.*\(1, 1\).*\(2, 1\)"):
        _controller(toy, ca.Function("fo", [x], [x]))
    with pytest.raises(BalustradeError, match="backup.*free symbols"):
        _controller(toy, ca.Function("ff", [x], [x[0] + y], {"allow_free": True}))
    with pytest.raises(BalustradeError, match="backup must be"):
        _controller(toy, 3.0)


class _PyLaw(ca.Callback):
    """A backup whose body is Python inside a casadi.Function (cannot be emitted)."""

    def __init__(self) -> None:
        ca.Callback.__init__(self)
        self.construct("pylaw", {})

    def get_n_in(self) -> int:
        return 1

    def get_n_out(self) -> int:
        return 1

    def get_sparsity_in(self, i: int) -> ca.Sparsity:
        return ca.Sparsity.dense(2, 1)

    def get_sparsity_out(self, i: int) -> ca.Sparsity:
        return ca.Sparsity.dense(1, 1)

    def eval(self, arg: list) -> list:
        return [-0.3 * arg[0][0]]


def test_emitter_refuses_a_python_backup_naming_it(toy, tmp_path) -> None:
    """A Python callable, or a casadi.Function that calls Python, is refused with a
    :class:`CodegenError` naming ``backup`` before anything is written."""
    py = _controller(toy, lambda x, u_p, k: toy.K @ x)
    with pytest.raises(CodegenError, match=r"backup is a Python callable.*\(K_b, k_b\)"):
        emit_rapsf(py, "rp", tmp_path / "a")
    cb = _PyLaw()
    xm = ca.MX.sym("x", 2)
    wrapped = ca.Function("wrapped", [xm], [cb(xm)])
    py = _controller(toy, wrapped)
    assert py.step(FAR, np.zeros(1))[0][0] == pytest.approx(-0.3 * FAR[0])  # Python runs it
    with pytest.raises(CodegenError, match="backup.*pylaw is a Python casadi.Callback"):
        emit_rapsf(py, "rq", tmp_path / "b")
    assert not (tmp_path / "a").exists() or not list((tmp_path / "a").iterdir())
    assert not (tmp_path / "b").exists() or not list((tmp_path / "b").iterdir())


# -- C = Python with forced fallbacks ---------------------------------------------------------
@pytest.fixture(scope="module", params=["affine", "function"])
def emitted(request, toy, tmp_path_factory: pytest.TempPathFactory) -> dict:
    kind = request.param
    py = _controller(toy, (K_B, K_B0) if kind == "affine" else _saturated())
    out = tmp_path_factory.mktemp(f"rapsf_backup_{kind}")
    em = emit_rapsf(py, "rb", out)
    lib = build(out, em.name, werror=True, extra_flags=link_flags(em.libraries))
    return {"py": py, "emitted": em, "lib": lib, "kind": kind}


def _same(py_out: tuple, c_out: tuple, where: object) -> None:
    (u1, i1), (u2, i2) = py_out, c_out
    assert np.max(np.abs(u1 - u2)) <= TOL, (where, u1, u2, i1.status, i2.status)
    assert i1.fallback == i2.fallback, (where, i1.fallback, i2.fallback)
    assert set(i1.uncertified) == set(i2.uncertified), (where, i1.uncertified, i2.uncertified)
    assert (i1.status == "ok") == (i2.status == "ok"), (where, i1.status, i2.status)
    assert i1.values.get("k_inf") == i2.values.get("k_inf"), (where, i1.values, i2.values)


def test_c_equals_python_with_forced_fallbacks(toy, emitted: dict) -> None:
    """A closed loop of the toy with a window of inflated ``s`` longer than ``N`` (stored
    plan, then the backup), a state outside ``X``, a NaN state and a falsified model: C and
    Python give the same input within 1e-6, fallback and status at every step, and every
    backup step applies the user's law (which differs from ``K x`` there)."""
    py, kind = emitted["py"], emitted["kind"]
    em = emitted["emitted"]
    assert em.manifest["backup"] == kind
    c = CRAPSF(emitted["lib"], host=py)
    py.reset()
    c.reset()
    s_true = py._s.copy()
    rng = np.random.default_rng(7)
    theta = np.array([1.2, 0.3])
    x, paths, differs = np.array([0.3, -0.2]), Counter(), 0

    def both(x: np.ndarray, u_p: np.ndarray, where: object) -> np.ndarray:
        nonlocal differs
        out_py, out_c = py.step(x, u_p), c.step(x, u_p)
        _same(out_py, out_c, where)
        paths[out_py[1].fallback] += 1
        if out_py[1].fallback == "backup":
            np.testing.assert_allclose(out_c[0], _law(x, kind), atol=TOL)
            differs += abs(out_c[0][0] - (toy.K @ np.where(np.isfinite(x), x, 0.0))[0]) > 1e-3
        return out_py[0]

    for k in range(14):
        py._s = c.host._s = np.full_like(s_true, S_INFLATED) if 4 <= k < 4 + N + 3 else s_true
        u = both(x, np.array([0.8 * np.sin(0.9 * k)]), k)
        x = toy.sys.step(x, u, theta, rng.uniform(-0.004, 0.004, 2))
    py._s = c.host._s = s_true
    for k, xk in enumerate((FAR, np.array([np.nan, 0.7]), np.array([0.4, 0.1]))):
        both(xk, np.zeros(1), ("special", k))
    py.falsified = c.host.falsified = True               # the estimator excluded every θ
    for k in range(2):
        both(np.array([0.5, -0.3 * k]), np.zeros(1), ("falsified", k))
    # the window: N − 1 stored-plan steps, then 4 backups; FAR: the stored plan (one was
    # stored after the window); the NaN state and the two falsified steps: the backup
    assert paths["stored_plan"] == N and paths[None] >= 6, paths
    assert paths["backup"] == 4 + 1 + 2, paths
    assert differs >= 6, differs


VALGRIND_MAIN = r"""
#include <math.h>
#include <stdio.h>
#include "rv.h"
int main(void) {
  double x[2] = {2.6, -2.4}, up[1] = {0.0}, u[1], theta[rv_NQ * rv_NTH], s[rv_NXR * rv_NTH];
  int k, st, bad = 0;
  rv_work* wk = rv_alloc();
  if (!wk) return 2;
  for (k = 0; k < rv_NQ * rv_NTH; ++k) theta[k] = 0.5 + 0.25 * (k % 2);
  for (k = 0; k < rv_NXR * rv_NTH; ++k) s[k] = 0.9;
  rv_step(x, up, theta, s, 0, u, &st, wk);            /* outside X: the backup function */
  bad += st != BAL_RAPSF_BACKUP || !isfinite(u[0]);
  x[0] = NAN;
  rv_step(x, up, theta, s, 0, u, &st, wk);            /* NaN state: the backup, NaN as 0 */
  bad += st != BAL_RAPSF_BAD_INPUT || !isfinite(u[0]);
  x[0] = 0.1;
  rv_step(x, up, theta, s, 1, u, &st, wk);            /* falsified: the backup */
  bad += st != BAL_RAPSF_FALSIFIED || !isfinite(u[0]);
  rv_step(x, up, theta, s, 0, u, 0, 0);               /* NULL status and work: NaN input */
  bad += !isnan(u[0]);
  rv_free(wk);
  printf("%d\n", bad);
  return bad;
}
"""

#: as in tests/test_rapsf_c_shrinking.py: DAQP (libdaqp.so of the casadi wheel) reads 8
#: bytes past one of its own workspace blocks while solving an infeasible QP; only reads
#: whose innermost frame is inside libdaqp are suppressed
DAQP_SUPPRESSION = """{
   daqp_update_LDL_remove_reads_past_its_workspace
   Memcheck:Addr8
   obj:*libdaqp.so*
   ...
}
"""


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("valgrind") is None, reason="valgrind not installed")
def test_valgrind_clean_with_a_backup_function(toy, tmp_path) -> None:
    """The backup function's memory (checkout in init, release in finalize) and its calls on
    the backup, bad-input and falsified paths are clean under valgrind; with no work memory
    the C cannot run the function and writes NaN, as rapsf.h says."""
    em = emit_rapsf(_controller(toy, _saturated()), "rv", tmp_path)
    (tmp_path / "vg_main.c").write_text(VALGRIND_MAIN)
    supp = tmp_path / "daqp.supp"
    supp.write_text(DAQP_SUPPRESSION)
    exe = build_executable(tmp_path, "vg_main.c",
                           extra_flags=["-g", "-O1", *link_flags(em.libraries)])
    run = run_under_valgrind(str(exe), suppressions=supp, timeout=600)
    assert run.returncode == 0, (run.stdout, run.stderr[-2000:])
    assert run.stdout.split() == ["0"], run.stdout
