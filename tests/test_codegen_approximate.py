"""Algorithm 7.5 ((7.6) then (7.5), certification shortcut) emitted as one C step equals
the Python controller on 1000 random states and in closed loop."""

from __future__ import annotations

import dataclasses
import shutil

import numpy as np
import pytest

from balustrade.codegen import CApproximatePCBFFilter, build, emit_approximate
from balustrade.codegen.build import build_executable, run_under_valgrind
from balustrade.codegen.runtime import mirror_c_retries
from balustrade.control.base import simulate
from balustrade.errors import CodegenError, ShapeError
from balustrade.examples.codegen import pendulum_approximate_filter
from balustrade.models.pendulum import pendulum


@pytest.fixture(scope="module")
def approx(tmp_path_factory: pytest.TempPathFactory) -> dict:
    py = pendulum_approximate_filter()
    # the reference: the Python backend with the retries of the C (eigen-clip, not IPOPT)
    py.decrease.compiled = mirror_c_retries(py.decrease.compiled)
    py.filter = mirror_c_retries(py.filter)
    out = tmp_path_factory.mktemp("approx")
    emitted = emit_approximate(py, "apx", out, dynamics=pendulum().function)
    return {"py": py, "lib": build(out, emitted.name, werror=True), "out": out}


def test_approximate_step_equals_python_on_1000_states(approx: dict) -> None:
    py, c = approx["py"], CApproximatePCBFFilter(approx["lib"])
    py.reset()
    rng = np.random.default_rng(0)
    X = rng.uniform([-0.7, -2.0], [0.7, 2.0], size=(1000, 2))
    UP = rng.uniform(-4, 4, size=(1000, 1))
    UP[::10] = 0.0  # proposals that often meet the decrease (the exact shortcut)
    for x, u_p in zip(X, UP):
        u1, i1 = py.step(x, u_p)
        u2, i2 = c.step(x, u_p)
        assert (i1.status, i1.fallback) == (i2.status, i2.fallback), (x, u_p)
        assert np.abs(u1 - u2).max() <= 1e-6, (x, u_p, u1, u2)
        if "dh" in i1.values:
            assert abs(i1.values["dh"] - i2.values["dh"]) <= 1e-6
            assert abs(i1.values["h_hat"] - i2.values["h_hat"]) <= 1e-6
    assert (py.n_certified, py.n_solved, py.n_fallbacks, py.n_proposal_feasible) == \
        (c.n_certified, c.n_solved, c.n_fallbacks, c.n_proposal_feasible)
    assert 0 < c.n_certified < 1000


def test_approximate_closed_loop_matches_python(approx: dict) -> None:
    py, c = approx["py"], CApproximatePCBFFilter(approx["lib"])
    system = pendulum()
    for x0 in ([0.3, 0.5], [-0.4, 1.0], [0.45, -1.2]):
        for proposal in (2.0, lambda k, x: 3.5 * np.sin(0.4 * k)):
            t1 = simulate(system, py, x0, 40, proposal=proposal)
            t2 = simulate(system, c, x0, 40, proposal=proposal)
            assert np.abs(t1.states - t2.states).max() <= 1e-6
            assert t1.fallbacks == t2.fallbacks and t1.statuses == t2.statuses


def test_approximate_refuses_ipopt(tmp_path) -> None:
    from balustrade.control.approximate import ApproximatePCBFFilter
    from balustrade.models.pendulum import pendulum_setup

    s = pendulum_setup()
    ctl = ApproximatePCBFFilter(pendulum(), s.U, lambda x: x[0] ** 2 - 1)  # IPOPT default
    with pytest.raises(CodegenError, match="ipopt"):
        emit_approximate(ctl, "a", tmp_path)


def test_approximate_exact_shortcut_rho_half(tmp_path) -> None:
    """With ρ = 1/2 the proposal often meets the decrease of (7.5) after (7.6): the exact
    shortcut applies it in C as in Python."""
    from balustrade.control.approximate import ApproximatePCBFFilter
    from balustrade.design.terminal_cbf import synthesize_terminal_cbf
    from balustrade.models.pendulum import pendulum_setup

    system, s = pendulum(), pendulum_setup()
    h = synthesize_terminal_cbf(system.A, system.B, s.X, s.U, delta_N=s.deltas[-1])
    py = ApproximatePCBFFilter(system, s.U, h, rho=0.5, target="fast-sqp")
    py.decrease.compiled = mirror_c_retries(py.decrease.compiled)
    py.filter = mirror_c_retries(py.filter)
    c = CApproximatePCBFFilter(build(emit_approximate(py, "apx_half", tmp_path).out_dir))
    rng = np.random.default_rng(1)
    for x, u_p in zip(rng.uniform([-0.7, -2.0], [0.7, 2.0], size=(300, 2)),
                      rng.uniform(-4, 4, size=(300, 1))):
        u1, i1 = py.step(x, u_p)
        u2, i2 = c.step(x, u_p)
        assert i1.status == i2.status and np.abs(u1 - u2).max() <= 1e-6
    assert py.n_proposal_feasible == c.n_proposal_feasible > 0


def test_approximate_non_finite_input_falls_back_as_python(approx: dict) -> None:
    """A NaN or inf state: the C step (BAL_APPROX_BAD_INPUT) applies what the Python
    controller applies (the proposal, non-finite entries as 0, clipped to U). A NaN or inf
    proposal with a finite state: both read it as 0 and run Algorithm 7.5 as usual, so
    the input is the filter's (status non_finite_proposal...). Never raises."""
    py, c = approx["py"], CApproximatePCBFFilter(approx["lib"])
    py.reset()
    c.reset()
    bad_x = [([np.nan, 0.0], 2.0), ([0.1, np.inf], 7.0), ([np.nan, np.nan], np.nan)]
    for x, u_p in bad_x:
        u1, i1 = py.step(np.array(x), np.array([u_p]))
        u2, i2 = c.step(np.array(x), np.array([u_p]))
        assert np.array_equal(u1, u2), (x, u_p, u1, u2)
        assert (i1.status, i1.fallback) == (i2.status, i2.fallback) == (
            "non_finite_state", "projected_proposal")
    assert py.n_fallbacks == c.n_fallbacks == len(bad_x)
    for x in ([0.1, 0.2], [0.45, 1.3], [-0.45, -1.3]):   # certified, filtered, filtered
        u0, i0 = py.step(np.array(x), np.array([0.0]))
        for u_p in (np.nan, np.inf, -np.inf):
            u1, i1 = py.step(np.array(x), np.array([u_p]))
            u2, i2 = c.step(np.array(x), np.array([u_p]))
            assert np.abs(u1 - u0).max() <= 1e-9 and np.abs(u1 - u2).max() <= 1e-6
            assert (i1.status, i1.fallback) == (i2.status, i2.fallback), (x, u_p)
            want = "non_finite_proposal" if i0.status == "ok" else \
                f"non_finite_proposal_{i0.status}"
            assert i1.status == want and i1.fallback == i0.fallback
    u1, i1 = py.step(np.array([0.3, 0.5]), np.array([3.5]))
    u2, i2 = c.step(np.array([0.3, 0.5]), np.array([3.5]))
    assert i1.status == i2.status and np.abs(u1 - u2).max() <= 1e-6
    with pytest.raises(ShapeError, match="CApproximatePCBFFilter.step: x"):
        c.step(np.zeros(3), np.array([1.0]))


def test_approximate_refuses_a_vector_h_the_c_cannot_hold(approx: dict, tmp_path) -> None:
    """A hand-edited deployment spec with a vector ĥ: the C reads one double for ĥ and
    ĥ(f(x, u)), so the emitter refuses it (naming the function) before writing anything."""
    import dataclasses

    import casadi as ca

    spec = approx["py"].deployment_spec()
    bad = dataclasses.replace(spec, h=lambda x: ca.vertcat(ca.sumsqr(x), x[0]))
    with pytest.raises(CodegenError, match="scalar.*apv_h"):
        emit_approximate(bad, "apv", tmp_path)


def _random_network(seed: int = 4, transform: str | None = "cbrt") -> object:
    """A 2 → 8 → 8 → 1 softplus network, ĥ = output³ (or the output), scaled inputs (a
    stand-in for a trained ĥ: the C must compute the same values, whatever the weights)."""
    from balustrade.learn.train import MLPModel

    rng = np.random.default_rng(seed)
    sizes = (2, 8, 8, 1)
    W = [rng.normal(0, 1.0, (b, a)) for a, b in zip(sizes[:-1], sizes[1:])]
    b = [rng.normal(0, 0.5, n) for n in sizes[1:]]
    b[-1] = b[-1] - 2.5  # ĥ <= 0 on part of the states: both certified and solved steps
    return MLPModel(W, b, np.array([0.05, -0.1]), np.array([0.4, 1.3]),
                    output_transform=transform)


@pytest.mark.parametrize("transform", ["cbrt", None])
def test_approximate_network_loops_equal_the_casadi_code(tmp_path, transform) -> None:
    """``network=``: the emitted C evaluates ĥ from the weights (bal/approx_net.c) and
    takes exactly the decisions of the CasADi-generated ĥ (same inputs, bit for bit) and
    of Python (1e-6), on certified and solved steps."""
    from balustrade.control.approximate import ApproximatePCBFFilter
    from balustrade.learn.export import to_casadi
    from balustrade.models.pendulum import pendulum_setup

    system, s, net = pendulum(), pendulum_setup(), _random_network(transform=transform)
    py = ApproximatePCBFFilter(system, s.U, to_casadi(net), rho=0.5, target="fast-sqp",
                               network=net)
    py.decrease.compiled = mirror_c_retries(py.decrease.compiled)
    py.filter = mirror_c_retries(py.filter)
    loops = emit_approximate(py, "apn", tmp_path / "loops")
    assert loops.manifest["network"] and "apn_NET_W" in \
        (loops.out_dir / "apn_config.h").read_text()
    spec = dataclasses.replace(py.deployment_spec(), network=None)
    plain = emit_approximate(spec, "apc", tmp_path / "plain")
    c_net = CApproximatePCBFFilter(build(loops.out_dir, werror=True))
    c_sx = CApproximatePCBFFilter(build(plain.out_dir, werror=True))
    rng = np.random.default_rng(2)
    for x, u_p in zip(rng.uniform([-0.7, -2.0], [0.7, 2.0], size=(300, 2)),
                      rng.uniform(-4, 4, size=(300, 1))):
        u0, i0 = py.step(x, u_p)
        u1, i1 = c_net.step(x, u_p)
        u2, i2 = c_sx.step(x, u_p)
        assert i1.status == i2.status and np.array_equal(u1, u2), (x, u_p, u1, u2)
        assert i0.status == i1.status and np.abs(u0 - u1).max() <= 1e-6, (x, u_p)
        if "h_hat" in i1.values:
            assert i1.values["h_hat"] == i2.values["h_hat"]
    assert 0 < c_net.n_certified < 300 and c_net.n_solved > 0


def test_approximate_network_must_be_the_one_h_came_from() -> None:
    from balustrade.control.approximate import ApproximatePCBFFilter
    from balustrade.errors import BalustradeError
    from balustrade.learn.export import to_casadi
    from balustrade.models.pendulum import pendulum_setup

    system, s = pendulum(), pendulum_setup()
    with pytest.raises(BalustradeError, match="network must be the MLP"):
        ApproximatePCBFFilter(system, s.U, to_casadi(_random_network(4)), target="fast-sqp",
                              network=_random_network(5))
    with pytest.raises(BalustradeError, match="network must be the MLP"):
        ApproximatePCBFFilter(system, s.U, to_casadi(_random_network(4)), target="fast-sqp",
                              network=np.zeros(3))


def test_network_softplus_threshold_is_emitted_from_the_learn_constant(tmp_path) -> None:
    """bal/approx_net.c's softplus threshold is ``<name>_NET_THRESHOLD``, emitted from
    ``balustrade.learn.train.SOFTPLUS_THRESHOLD`` (it was a literal 20.0 in the C and in
    the emitter's numpy mirror)."""
    import re

    from balustrade.codegen.emit import _network_forward
    from balustrade.control.approximate import ApproximatePCBFFilter
    from balustrade.learn.export import to_casadi
    from balustrade.learn.train import SOFTPLUS_THRESHOLD
    from balustrade.models.pendulum import pendulum_setup

    net = _random_network()
    py = ApproximatePCBFFilter(pendulum(), pendulum_setup().U, to_casadi(net), rho=0.5,
                               target="fast-sqp", network=net)
    cfg = (emit_approximate(py, "apt", tmp_path).out_dir / "apt_config.h").read_text()
    (value,) = re.findall(r"#define apt_NET_THRESHOLD \(?([-0-9.e+]+)", cfg)
    assert float(value) == SOFTPLUS_THRESHOLD == net.softplus_threshold
    # the emitter's numpy mirror follows the network's threshold
    X = np.random.default_rng(0).uniform(-1, 1, (5, 2))
    big = _random_network()
    big.weights = [20.0 * W for W in big.weights]   # pre-activations well above 3
    big.softplus_threshold = 3.0
    lin = _random_network()
    lin.weights = big.weights
    assert not np.allclose(_network_forward(big, X), _network_forward(lin, X))
    assert np.allclose(_network_forward(lin, X), lin(X), rtol=1e-12)


VALGRIND_MAIN = r"""
#include <math.h>
#include <stdio.h>
#include "apx.h"
int main(void) {
  double x[2], u[1], h, up[1];
  int k, st, bad = 0;
  apx_work* wk = apx_alloc();
  if (!wk) return 2;
  for (k = 0; k < 40; ++k) {
    x[0] = -0.7 + 0.035 * k; x[1] = 2.0 - 0.1 * k; up[0] = -4.0 + 0.2 * k;
    apx_set_certify(wk, k % 2);
    apx_step(x, up, u, &h, &st, wk);
    bad += !isfinite(u[0]);
  }
  x[0] = NAN;
  apx_step(x, up, u, &h, &st, wk);
  bad += st != BAL_APPROX_BAD_INPUT;
  apx_free(wk);
  printf("%d\n", bad);
  return bad;
}
"""


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("valgrind") is None, reason="valgrind not installed")
def test_approximate_valgrind_clean(approx: dict) -> None:
    """bal/approx.c under valgrind (audit C, session 14): 40 steps with and without the
    certificate (7.5)/(7.6), then a NaN state; no memory error, no definite leak."""
    out = approx["out"]
    (out / "vg_main.c").write_text(VALGRIND_MAIN)
    exe = build_executable(out, "vg_main.c", extra_flags=["-g", "-O1"])
    run = run_under_valgrind(str(exe), timeout=600)
    assert run.returncode == 0, (run.stdout, run.stderr[-2000:])


def test_a_converged_filter_outside_u_is_filter_failed_in_both(tmp_path) -> None:
    """A (7.5) whose solver converges to an input outside ``U`` has not solved (7.5) (its
    constraint ``u ∈ U`` fails): Python and C both apply the (7.6) minimizer (Proposition
    7.3) with status ``"filter_failed"`` (Python used to say ``"filter_optimal"``). Forced
    in both the same way: (7.5) compiled over a wider input box than the filter's ``U``,
    so that its optimum lies outside ``U`` when ``u_p`` does."""
    from balustrade.backends import compile
    from balustrade.backends.casadi_fast import FastNLP
    from balustrade.dsl.sets import Box
    from balustrade.problems.approximate import approximate_filter_problem

    py = pendulum_approximate_filter()
    U = py.U
    wide = Box(U.lb - 2.0, U.ub + 2.0, name="U_wide")
    py.filter = mirror_c_retries(compile(approximate_filter_problem(py.system, wide, py.h),
                                         py.target))
    py._fast_filter = FastNLP(py.filter)
    py.decrease.compiled = mirror_c_retries(py.decrease.compiled)
    emitted = emit_approximate(py, "apxwide", tmp_path, dynamics=pendulum().function)
    c = CApproximatePCBFFilter(build(tmp_path, emitted.name, werror=True))
    rng = np.random.default_rng(2)
    outside = 0
    for x, u_p in zip(rng.uniform([-0.7, -2.0], [0.7, 2.0], size=(60, 2)),
                      rng.choice([-1.0, 1.0], size=(60, 1)) * rng.uniform(U.ub[0] + 0.5,
                                                                         U.ub[0] + 1.5,
                                                                         size=(60, 1))):
        u1, i1 = py.step(x, u_p)
        u2, i2 = c.step(x, u_p)
        assert (i1.status, i1.fallback) == (i2.status, i2.fallback), (x, u_p)
        assert np.abs(u1 - u2).max() <= 1e-6, (x, u_p, u1, u2)
        if i1.fallback == "max_decrease_solution":
            assert i1.status == "filter_failed" and U.contains(u1)
            outside += 1
    assert outside >= 10
