"""Algorithm 8.7 on the Chronos Frenet model (thesis §8.4) in C: the emitted grid filter
(:func:`balustrade.codegen.emit_grid`, the learned ``ĥ`` and the Euler Frenet model with the
oval's curvature ``κ(s)``) built with ``-Werror`` takes the inputs and statuses of
:class:`~balustrade.control.approximate.GridPCBFFilter` on 1000 random states and along a
closed loop of scenario 1, and runs valgrind-clean. The network is a freshly initialised
4 × 32 softplus net (no committed artifact); the Python filter runs both with the CasADi
``ĥ`` and with the batched numpy ``ĥ`` (``h_rows``)."""

from __future__ import annotations

import shutil
import subprocess

import numpy as np
import pytest

from balustrade.codegen import CGridPCBFFilter, build, build_executable, emit_grid
from balustrade.codegen import status as S
from balustrade.errors import BalustradeError
from balustrade.learn.train import MLPModel
from balustrade.models.track import Track, oval
from balustrade.reproduce.chronos import (
    SCENARIOS,
    c_grid_filter,
    closed_loop,
    compare_c,
    grid_filter,
    h_function,
    h_rows,
)

TRACK = oval()
#: states near the track: s over one lap and beyond (wrap), |e| <= 0.3, |μ| <= 0.8, …
LO = np.array([-1.0, -0.3, -0.8, 0.2, -0.3, -2.0])
HI = np.array([TRACK.length + 1.0, 0.3, 0.8, 2.0, 0.3, 2.0])


def network(seed: int = 0, c: float = 0.28) -> MLPModel:
    """A 4 × 32 softplus net on the Frenet state built here (no training, no committed
    artifact), ``ĥ = net³`` as in the reproduction. Small random weights everywhere, and
    two units per layer carrying ``softplus(±a (e + 0.6 μ + 0.15 ω))`` (scaled state) to
    the output: ``ĥ ≈ c·|·| − 1``, a barrier-like bowl around the centre line, so that
    the filter steers (and both outcomes of the decrease test occur)."""
    rng = np.random.default_rng(seed)
    widths = [6, 32, 32, 32, 32, 1]
    W = [0.2 * rng.normal(0.0, np.sqrt(2.0 / (a + b)), (b, a))
         for a, b in zip(widths, widths[1:])]
    b = [0.2 * rng.normal(0.0, 0.1, n) for n in widths[1:]]
    for sign, r in ((1.0, 0), (-1.0, 1)):
        W[0][r] = 0.0
        W[0][r, [1, 2, 5]] = sign * 4.0 * np.array([1.0, 0.6, 0.15])
        for k in (1, 2, 3):
            W[k][r], W[k][:, r], b[k][r] = 0.0, 0.0, 0.0
            W[k][r, r] = 1.0
    W[4][0, :2], b[4][0] = c, -1.0
    return MLPModel(W, b, 0.5 * (LO + HI), 0.5 * (HI - LO), output_transform="cbrt")


@pytest.fixture(scope="module")
def chronos_c(tmp_path_factory: pytest.TempPathFactory) -> dict:
    model = network()
    h = h_function(model, TRACK)
    py = grid_filter(h, TRACK)
    fast = grid_filter(h, TRACK, h_rows(model, TRACK))
    d = tmp_path_factory.mktemp("chronos_c")
    em = emit_grid(py, "chronos_grid", d, dynamics=py.system.function)
    return {"model": model, "h": h, "py": py, "fast": fast, "dir": d,
            "lib": build(d, em.name, werror=True)}


def _same(py, c, x: np.ndarray, u_p: np.ndarray) -> str:
    u1, i1 = py.step(x, u_p)
    u2, i2 = c.step(x, u_p)
    assert np.abs(u1 - u2).max() <= 1e-6, (x, u_p, u1, u2)
    assert (i1.status, i1.fallback) == (i2.status, i2.fallback), (x, u_p)
    assert abs(i1.values["h_hat"] - i2.values["h_hat"]) <= 1e-6 * max(1.0, abs(i1.values["h_hat"]))
    assert i1.values["n_candidates"] == i2.values["n_candidates"]
    assert np.abs(py.u_prev - c.u_prev).max() <= 1e-6
    return i1.status


def test_chronos_c_matches_python_on_1000_states(chronos_c: dict) -> None:
    py, fast = chronos_c["py"], chronos_c["fast"]
    c = CGridPCBFFilter(chronos_c["lib"])
    for f in (py, fast, c):
        f.reset()
    rng = np.random.default_rng(1)
    states = rng.uniform(LO, HI, (1000, 6))
    # proposals outside U = [0, 1] × [−0.4, 0.4] too: clipping of the candidates
    proposals = rng.uniform([-0.3, -0.6], [1.3, 0.6], (1000, 2))
    statuses = []
    for x, u_p in zip(states, proposals):
        statuses.append(_same(py, c, x, u_p))
        u3, i3 = fast.step(x, u_p)  # the batched numpy ĥ takes the same decisions
        assert np.array_equal(u3, c.u_prev) and i3.status == statuses[-1]
    assert set(statuses) == {"ok", "no_decreasing_candidate"}  # both branches of step 3
    assert (py.n_steps, py.n_decrease_infeasible) == (c.n_steps, c.n_decrease_infeasible)
    assert fast.n_decrease_infeasible == c.n_decrease_infeasible


def test_chronos_c_closed_loop_matches_python(chronos_c: dict, tmp_path) -> None:
    """300 steps of the constant-left-steer scenario on the Cartesian plant: the C filter
    loaded through :func:`~balustrade.codegen.accelerate` (with ``-Werror``) and the
    Python filter with the batched ``ĥ`` give the same inputs, states and statuses."""
    fast = chronos_c["fast"]
    c = c_grid_filter(fast, tmp_path)
    assert isinstance(c, CGridPCBFFilter)
    fast.reset()
    run_py = closed_loop(TRACK, SCENARIOS["left"], fast, max_steps=300)
    run_c = closed_loop(TRACK, SCENARIOS["left"], c, max_steps=300)
    assert len(run_py["u"]) == len(run_c["u"]) == 300
    assert np.abs(run_py["u"] - run_c["u"]).max() <= 1e-6
    assert np.abs(run_py["frenet"] - run_c["frenet"]).max() <= 1e-6
    assert np.array_equal(run_py["status"], run_c["status"])
    assert set(run_py["status"]) == {"ok", "no_decreasing_candidate"}
    assert np.abs(run_py["u"] - run_py["u_p"]).max() > 0.2  # the filter steered
    # the replay of reproduce chronos: lockstep, interleaved timing
    rep = compare_c(fast, c, run_py["frenet"][:300], run_py["u_p"])
    assert rep["steps"] == 300 and rep["statuses_equal"]
    assert rep["max_input_difference"] <= 1e-6
    assert rep["c_call_median_ms"] <= rep["c_step_median_ms"]


def test_chronos_c_uses_the_tracks_curvature(chronos_c: dict, tmp_path) -> None:
    """The emitted dynamics is the Frenet model of *this* track: ``<name>_dynamics`` equals
    the Python model on states over the whole lap (curvature ramps, arcs, wrap of ``s``),
    and a filter for another track (a tighter oval) emits and matches its own Python."""
    import ctypes

    py = chronos_c["py"]
    lib = ctypes.CDLL(str(chronos_c["lib"]))
    assert hasattr(lib, "chronos_grid_dynamics")
    other = Track([1.5, np.pi * 0.4, 1.5, np.pi * 0.4], [0.0, 2.5, 0.0, 2.5], width=0.5,
                  transition=0.1, name="tight")
    model = chronos_c["model"]
    py2 = grid_filter(h_function(model, other), other, h_rows(model, other))
    em = emit_grid(py2, "tight_grid", tmp_path)
    c2 = CGridPCBFFilter(build(em.out_dir, em.name, werror=True))
    rng = np.random.default_rng(5)
    differs = 0
    for x in rng.uniform(LO, HI, (200, 6)):
        u_p = rng.uniform([0.0, -0.4], [1.0, 0.4])
        _same(py2, c2, x, u_p)
        differs += not np.allclose(py.system.step(x, u_p), py2.system.step(x, u_p))
    assert differs > 0  # the two tracks' models are not the same


def test_reproduction_reports_the_c_filter(chronos_c: dict, tmp_path, monkeypatch) -> None:
    """What ``reproduce chronos`` writes under ``c_filter``: C = Python along scenario 1
    (closed loop and replay) with both step times; without a C compiler, why not."""
    from balustrade.reproduce.chronos import _c_filter

    fast = chronos_c["fast"]
    fast.reset()
    run_py = closed_loop(TRACK, SCENARIOS["p-controller"], fast, max_steps=150)
    res = _c_filter(tmp_path, TRACK, fast, run_py)
    assert res["status"] == "built" and res["c_equals_python"]
    assert res["closed_loop_p_controller"]["steps"] == 150
    assert res["replay_p_controller"]["c_step_median_ms"] > 0
    monkeypatch.setenv("CC", "no-such-compiler-xyz")
    res = _c_filter(tmp_path, TRACK, fast, run_py)
    assert res["status"].startswith("not run") and "no-such-compiler-xyz" in res["status"]


DRIVER = r"""
#include <math.h>
#include <stdio.h>
#include "chronos_grid.h"
int main(void) {
  double x[6] = {1.9, 0.05, 0.1, 0.8, 0.0, 0.0}, xn[6] = {NAN, 0, 0, 1, 0, 0};
  double u_p[2] = {0.3, 0.0}, u[2] = {0, 0}, h = 0.0;
  int status = -9, k;
  chronos_grid_work* wk = chronos_grid_alloc();
  if (!wk) return 2;
  for (k = 0; k < 30; ++k) {
    chronos_grid_step(x, u_p, u, &h, &status, wk);
    printf("step %d %.17g %.17g %d\n", status, u[0], u[1], chronos_grid_n_candidates(wk));
    x[0] += 0.1;
    x[1] = 0.2 * sin(0.3 * k);
  }
  chronos_grid_step(xn, u_p, u, &h, &status, wk);
  printf("nan %d %.17g %.17g\n", status, u[0], u[1]);
  chronos_grid_free(wk);
  return 0;
}
"""


@pytest.mark.skipif(shutil.which("valgrind") is None, reason="valgrind not installed")
def test_chronos_c_driver_werror_valgrind(chronos_c: dict) -> None:
    d = chronos_c["dir"]
    (d / "driver.c").write_text(DRIVER)
    exe = build_executable(d, main="driver.c", werror=True)
    cmd = ["valgrind", "--error-exitcode=9", "--leak-check=full", "-q", str(exe)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr
    lines = [ln.split() for ln in proc.stdout.splitlines()]
    assert len(lines) == 31
    assert all(1 <= int(ln[4]) <= 55 for ln in lines[:30])
    assert lines[-1][:2] == ["nan", str(S.code_of(S.GRID, "non_finite_state"))]
    assert lines[-1][2:] == lines[-2][2:4]  # u_{k-1} kept


def test_h_rows_must_equal_h(chronos_c: dict) -> None:
    model, h = chronos_c["model"], chronos_c["h"]
    with pytest.raises(BalustradeError, match="h_rows must equal"):
        grid_filter(h, TRACK, h_rows(network(seed=7), TRACK))
    with pytest.raises(BalustradeError, match="h_rows must equal"):
        grid_filter(h, TRACK, lambda X: model(X)[:1])  # wrong shape
    with pytest.raises(BalustradeError, match="callable"):
        grid_filter(h, TRACK, 3.0)
