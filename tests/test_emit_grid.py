"""Algorithm 8.7 in C (:func:`balustrade.codegen.emit_grid`, ``bal/grid.c``,
:class:`balustrade.codegen.CGridPCBFFilter`): built with ``-Werror``, the same inputs,
statuses and ``ĥ`` as :class:`~balustrade.control.approximate.GridPCBFFilter` on 1000 states
and along closed loops of the pendulum, valgrind-clean when valgrind is installed."""

from __future__ import annotations

import dataclasses
import shutil
import subprocess

import casadi as ca
import numpy as np
import pytest

from balustrade.codegen import CGridPCBFFilter, build, build_executable, emit_grid
from balustrade.codegen import status as S
from balustrade.control import simulate
from balustrade.control.approximate import GridPCBFFilter
from balustrade.dsl.sets import Polytope
from balustrade.errors import CodegenError, ShapeError
from balustrade.learn.export import to_casadi
from balustrade.learn.train import MLPModel
from balustrade.models.pendulum import pendulum, pendulum_setup

SYS = pendulum()
U = pendulum_setup().U
P = np.array([[4.246, 0.212], [0.212, 0.460]])


def random_network(widths: tuple[int, ...], seed: int = 0) -> ca.Function:
    """A softplus MLP with random weights (as benchmarks/bench_approximate.py), ``ĥ``
    shifted so that it is negative near the origin."""
    rng = np.random.default_rng(seed)
    sizes = (2, *widths, 1)
    W = [rng.normal(0, np.sqrt(2 / (a + b)), (b, a)) for a, b in zip(sizes[:-1], sizes[1:])]
    b = [rng.normal(0, 0.1, n) for n in sizes[1:]]
    net = to_casadi(MLPModel(W, b, np.zeros(2), np.array([0.5, 1.5])))
    x = ca.SX.sym("x", 2)
    return ca.Function("h_net", [x], [ca.mtimes([x.T, P, x]) - 1 + 0.2 * net(x)])


def h_wavy(x):
    return ca.mtimes([x.T, P, x]) - 1 + 0.3 * ca.sin(3 * x[0]) * ca.cos(2 * x[1])


@pytest.fixture(scope="module")
def grid_c(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A 4 × 32 network, 101 grid points (spacing 0.01), and ``h_wavy`` with 11 points
    starting at the upper bound of U (clipping and duplicates)."""
    out = {}
    for key, h, kw in (
            ("net", random_network((32, 32, 32, 32)),
             dict(half_width=0.5, spacing=0.01, rho=0.9)),
            ("wavy", h_wavy, dict(half_width=0.5, spacing=0.1, rho=0.8, u_init=2.9))):
        py = GridPCBFFilter(SYS, U, h, **kw)
        d = tmp_path_factory.mktemp(f"grid_{key}")
        em = emit_grid(py, f"g_{key}", d, dynamics=SYS.function)
        out[key] = {"py": py, "lib": build(d, em.name, werror=True), "dir": d, "em": em}
    return out


def _compare(py: GridPCBFFilter, c: CGridPCBFFilter, x: np.ndarray, u_p: object) -> None:
    u1, i1 = py.step(x, u_p)
    u2, i2 = c.step(x, u_p)
    assert np.abs(u1 - u2).max() <= 1e-6, (x, u_p, u1, u2)
    assert (i1.status, i1.fallback) == (i2.status, i2.fallback)
    assert i1.values.keys() == i2.values.keys()
    for k, v in i1.values.items():
        assert abs(v - i2.values[k]) <= 1e-6 * max(1.0, abs(v)), k
    assert np.abs(py.u_prev - c.u_prev).max() <= 1e-6


@pytest.mark.parametrize("key", ["net", "wavy"])
def test_grid_c_matches_python_on_1000_states(grid_c: dict, key: str) -> None:
    g = grid_c[key]
    py, c = g["py"], CGridPCBFFilter(g["lib"])
    py.reset()
    rng = np.random.default_rng(1)
    states = rng.uniform([-1.0, -3.0], [1.0, 3.0], (1000, 2))
    proposals = rng.uniform(-5.0, 5.0, 1000)  # outside U = [-3, 3] too: clipping
    for x, u_p in zip(states, proposals):
        _compare(py, c, x, u_p)
    assert (py.n_steps, py.n_decrease_infeasible) == (c.n_steps, c.n_decrease_infeasible)
    assert 0 < c.n_decrease_infeasible < 1000  # both branches of step 3 ran
    py.reset()
    c.reset()
    assert np.array_equal(py.u_prev, c.u_prev) and c.n_steps == 0


@pytest.mark.parametrize("key", ["net", "wavy"])
def test_grid_c_closed_loop_matches_python(grid_c: dict, key: str) -> None:
    g = grid_c[key]
    py, c = g["py"], CGridPCBFFilter(g["lib"])
    for x0 in ([0.3, 0.5], [-0.4, 1.0], [0.45, -1.2]):
        for proposal in (2.0, lambda k, x: 3.5 * np.sin(0.4 * k)):
            py.reset()
            c.reset()
            t1 = simulate(SYS, py, x0, 40, proposal=proposal)
            t2 = simulate(SYS, c, x0, 40, proposal=proposal)
            assert np.abs(t1.states - t2.states).max() <= 1e-6
            assert np.abs(t1.inputs - t2.inputs).max() <= 1e-6
            assert t1.fallbacks == t2.fallbacks and t1.statuses == t2.statuses


def test_grid_c_non_finite_inputs(grid_c: dict) -> None:
    g = grid_c["wavy"]
    py, c = g["py"], CGridPCBFFilter(g["lib"])
    py.reset()
    x = np.array([0.2, 0.1])
    _compare(py, c, x, 1.0)
    u_before = c.u_prev
    u, info = c.step([np.nan, 0.0], 1.0)  # keeps u_{k-1}, as the Python filter
    _, info_py = py.step([np.nan, 0.0], 1.0)
    assert np.array_equal(u, u_before) and info.status == info_py.status == "non_finite_state"
    assert info.fallback == info_py.fallback == "previous_input"
    _compare(py, c, x, np.inf)  # read as 0: "non_finite_proposal[_...]"
    assert c.step(x, np.nan)[1].status.startswith("non_finite_proposal")
    with pytest.raises(ShapeError):
        c.step(np.zeros(3), 1.0)


def test_grid_emit_refuses_non_box_U(tmp_path) -> None:
    poly = Polytope(np.array([[1.0], [-1.0]]), np.array([3.0, 3.0]))
    g = GridPCBFFilter(SYS, poly, h_wavy, half_width=0.5, spacing=0.1)
    with pytest.raises(CodegenError, match="must be a Box"):
        emit_grid(g, "gp", tmp_path)
    with pytest.raises(CodegenError, match="GridPCBFFilter"):
        emit_grid(object(), "gp", tmp_path)


def test_grid_emit_refuses_a_hand_built_spec_the_c_cannot_hold(tmp_path) -> None:
    """A GridDeployment written by hand: a vector ĥ would overrun the one double the C
    reads, arrays of the wrong size would not fit their ``nu``-sized C arrays."""
    spec = GridPCBFFilter(SYS, U, h_wavy, half_width=0.5, spacing=0.1).deployment_spec()
    bad = {"h": lambda x: ca.vertcat(ca.sumsqr(x), x[0]), "scale": np.ones(2),
           "u_init": np.zeros(3), "offsets": np.zeros((4, 2))}
    for field, value in bad.items():
        with pytest.raises(CodegenError, match="scalar|entries|shape"):
            emit_grid(dataclasses.replace(spec, **{field: value}), "gb", tmp_path / field)
    with pytest.raises(CodegenError, match="scale > 0"):
        emit_grid(dataclasses.replace(spec, scale=np.zeros(1)), "gb", tmp_path / "z")


DRIVER = r"""
#include <math.h>
#include <stdio.h>
#include "g_wavy.h"
int main(void) {
  double x[2] = {0.2, 0.1}, xn[2] = {NAN, 0.0}, u_p = 1.0, u = 0.0, h = 0.0;
  int status = -9, k;
  g_wavy_work* wk = g_wavy_alloc();
  if (!wk) return 2;
  for (k = 0; k < 20; ++k) {
    g_wavy_step(x, &u_p, &u, &h, &status, wk);
    printf("step %d %.17g %d\n", status, u, g_wavy_n_candidates(wk));
    x[0] *= 1.1;
  }
  g_wavy_step(xn, &u_p, &u, &h, &status, wk);
  printf("nan %d %.17g\n", status, u);
  status = g_wavy_step(0, &u_p, &u, &h, &status, wk);
  printf("null %d\n", status);
  g_wavy_free(wk);
  return 0;
}
"""


def test_grid_c_driver_werror_valgrind(grid_c: dict) -> None:
    d = grid_c["wavy"]["dir"]
    (d / "driver.c").write_text(DRIVER)
    exe = build_executable(d, main="driver.c", werror=True)
    cmd = [str(exe)]
    if shutil.which("valgrind"):
        cmd = ["valgrind", "--error-exitcode=9", "--leak-check=full", "-q", *cmd]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr
    lines = [ln.split() for ln in proc.stdout.splitlines()]
    bad = str(S.code_of(S.GRID, "non_finite_state"))
    assert lines[-1] == ["null", bad]
    assert lines[-2][:2] == ["nan", bad] and lines[-2][2] == lines[-3][2]  # u_{k-1} kept
    assert all(int(ln[3]) <= 11 for ln in lines[:20])


def test_grid_c_ties_go_to_the_first_candidate(tmp_path) -> None:
    """``u_p`` halfway between two admissible candidates (exact binary fractions): the
    lexicographically first one, as numpy's argmin; so is the first of equal ``ĥ`` values
    when none decreases."""
    for h, u_p, expect in ((lambda x: ca.sumsqr(x) - 100.0, 0.125, 0.0),
                           (lambda x: 1.0 + 0 * x[0], 0.3, -0.5)):
        py = GridPCBFFilter(SYS, U, h, half_width=0.5, spacing=0.25, rho=0.9)
        em = emit_grid(py, "gt", tmp_path / str(expect).replace("-", "m").replace(".", "_"))
        c = CGridPCBFFilter(build(em.out_dir, em.name, werror=True))
        u1, _ = py.step(np.array([0.1, 0.2]), u_p)
        u2, _ = c.step(np.array([0.1, 0.2]), u_p)
        assert u1[0] == u2[0] == expect


def test_grid_c_two_inputs_matches_python(tmp_path) -> None:
    """Two inputs (the bicycle): candidates clipped on both axes reorder and merge, so the
    lexicographic sort and deduplication of the C are exercised."""
    from balustrade.models.bicycle import bicycle, bicycle_sets

    system = bicycle()
    _, U2, _ = bicycle_sets()
    Q = np.diag([25.0, 2.0, 1.0, 2.0])
    x_ref = np.array([0.0, 0.0, 0.9, 0.0])

    def h(x):
        d = x - x_ref
        return ca.mtimes([d.T, Q, d]) - 1 + 0.2 * ca.sin(4 * x[1])

    py = GridPCBFFilter(system, U2, h, half_width=[0.2, 1.0], spacing=[0.05, 0.25], rho=0.9,
                        u_init=[0.28, 1.9])
    em = emit_grid(py, "gb", tmp_path)
    c = CGridPCBFFilter(build(em.out_dir, em.name, werror=True))
    rng = np.random.default_rng(3)
    lo, hi = np.array([-0.3, -0.7, 0.3, -0.7]), np.array([0.3, 0.7, 1.5, 0.7])
    for x in rng.uniform(lo, hi, (300, 4)):
        _compare(py, c, x, rng.uniform([-0.5, -3.0], [0.5, 3.0]))
    assert 0 < c.n_decrease_infeasible < 300
