"""Python closed loops on the emitted C (:func:`balustrade.codegen.accelerate`): the same
trace as the Python controller, the build cached by the hash of the generated sources, warm
primal–dual starts kept in the C work struct across steps and cleared by ``reset()``, and a
CodegenError saying why for a controller that cannot be emitted."""

from __future__ import annotations

import shutil

import casadi as ca
import numpy as np
import pytest

from balustrade.codegen import CGridPCBFFilter, CPCBFSafetyFilter, accelerate
from balustrade.codegen.accelerate import register, registered, source_hash
from balustrade.codegen.build import BASE_FLAGS, THREAD_FLAGS
from balustrade.control import PCBFSafetyFilter, simulate
from balustrade.control.approximate import GridPCBFFilter
from balustrade.design.terminal_cbf import synthesize_terminal_cbf
from balustrade.errors import CodegenError
from balustrade.models.pendulum import pendulum, pendulum_setup

SYS, SETUP = pendulum(), pendulum_setup()
P = np.array([[4.246, 0.212], [0.212, 0.460]])


def _args() -> tuple:
    s = SETUP
    h_f = synthesize_terminal_cbf(SYS.A, SYS.B, s.X, s.U, delta_N=s.deltas[-1])
    return (SYS, s.X, s.U, h_f, s.N, s.deltas)


@pytest.fixture(scope="module")
def pcbf(tmp_path_factory: pytest.TempPathFactory) -> dict:
    build_dir = tmp_path_factory.mktemp("accelerate")
    py = PCBFSafetyFilter.build(*_args(), alpha_f=SETUP.alpha_f, slack_norm=1,
                                target="fast-sqp")
    return {"py": py, "c": accelerate(py, build_dir=build_dir, werror=True),
            "dir": build_dir}


def test_accelerated_pcbf_trace_matches_python(pcbf: dict) -> None:
    py, c = pcbf["py"], pcbf["c"]
    assert isinstance(c, CPCBFSafetyFilter) and not c.accelerated["cached"]
    for x0 in ([0.0, 1.0], [0.3, -1.5], [-0.2, 2.0]):
        for proposal in (2.0, lambda k, x: 3.0 * np.sin(0.3 * k)):
            py.reset()
            c.reset()
            t1 = simulate(SYS, py, x0, 40, proposal=proposal)
            t2 = simulate(SYS, c, x0, 40, proposal=proposal)
            assert np.abs(t1.states - t2.states).max() <= 1e-6
            assert np.abs(t1.inputs - t2.inputs).max() <= 1e-6
            assert t1.statuses == t2.statuses and t1.fallbacks == t2.fallbacks


def test_second_call_hits_the_cache(pcbf: dict, tmp_path) -> None:
    first = pcbf["c"].accelerated
    lib = first["dir"] / "libbal_pcbf.so"
    mtime = lib.stat().st_mtime_ns
    again = accelerate(pcbf["py"], build_dir=pcbf["dir"], werror=True)
    assert again.accelerated["cached"] and again.accelerated["dir"] == first["dir"]
    assert again.accelerated["hash"] == first["hash"]
    assert lib.stat().st_mtime_ns == mtime  # not rebuilt
    # other flags are another build: the cached hash is that of exactly these sources and
    # flags (the library left out), and the same sources with another flag hash otherwise
    src = tmp_path / "src"
    shutil.copytree(first["dir"], src, ignore=shutil.ignore_patterns("*.so"))
    flags = (*BASE_FLAGS, *THREAD_FLAGS, "-Werror")
    assert source_hash(src, flags) == first["hash"]
    assert source_hash(src, (*flags, "-O2")) != first["hash"]
    x = np.array([0.1, 0.5])
    pcbf["c"].reset()
    u1, _ = pcbf["c"].step(x, 2.0)
    u2, _ = again.step(x, 2.0)
    assert np.array_equal(u1, u2)


def test_warm_starts_kept_across_steps_and_cleared_by_reset(pcbf: dict) -> None:
    c = pcbf["c"]
    c.reset()
    cold = c.slack.warm_start()
    assert not cold["lam_g0"].any() and not cold["lam_x0"].any()
    x = np.array([0.2, 1.0])
    for _ in range(3):
        u, info = c.step(x, 2.0)
        assert info.status == "ok"
        for view in (c.slack, c.filter):
            ws = view.warm_start()
            # the next solve starts from this solution, primal and dual
            assert np.array_equal(ws["x0"], ws["x"])
            assert np.array_equal(ws["lam_g0"], ws["lam_g"])
            assert np.array_equal(ws["lam_x0"], ws["lam_x"])
            assert np.abs(ws["lam_g0"]).max() > 0  # active constraints: real multipliers
        x = SYS.step(x, u)
    c.reset()
    for view in (c.slack, c.filter):
        ws = view.warm_start()
        assert not ws["lam_g0"].any() and not ws["lam_x0"].any()
        assert not np.array_equal(ws["x0"], ws["x"])


def h_wavy(x):
    return ca.mtimes([x.T, P, x]) - 1 + 0.3 * ca.sin(3 * x[0]) * ca.cos(2 * x[1])


def test_accelerated_grid_filter_matches_python(tmp_path) -> None:
    class MyGrid(GridPCBFFilter):  # a subclass uses the emitter of its base (MRO)
        pass

    py = MyGrid(SYS, SETUP.U, h_wavy, half_width=0.5, spacing=0.1, rho=0.8)
    c = accelerate(py, build_dir=tmp_path)
    assert isinstance(c, CGridPCBFFilter)
    py.reset()
    t1 = simulate(SYS, py, [0.4, -1.0], 40, proposal=2.5)
    t2 = simulate(SYS, c, [0.4, -1.0], 40, proposal=2.5)
    assert np.abs(t1.states - t2.states).max() <= 1e-6
    assert t1.statuses == t2.statuses and t1.fallbacks == t2.fallbacks


def test_controller_that_cannot_be_emitted_raises(tmp_path) -> None:
    class Mine:
        def step(self, x, u_p):
            return u_p, None

        def reset(self) -> None:
            pass

    with pytest.raises(CodegenError, match="no C emitter for a Mine"):
        accelerate(Mine(), build_dir=tmp_path)
    cvx = PCBFSafetyFilter.build(*_args(), alpha_f=SETUP.alpha_f, slack_norm=1,
                                 target="cvxpy")
    with pytest.raises(CodegenError, match="CasADi backend"):
        accelerate(cvx, build_dir=tmp_path)
    with pytest.raises(CodegenError, match="C identifier"):
        register(Mine, lambda c, n, d: None, lambda p, m: None, "not an identifier")
    grid = GridPCBFFilter(SYS, SETUP.U, h_wavy, half_width=0.5, spacing=0.1, rho=0.8)
    with pytest.raises(CodegenError, match="build_dir must be a path"):
        accelerate(grid, build_dir=123)
    with pytest.raises(CodegenError, match="extra_flags must be a tuple of strings"):
        accelerate(grid, build_dir=tmp_path, extra_flags="-O2")  # not '-', 'O', '2'
    assert Mine not in registered()


def test_accelerated_approximate_filter_matches_python(tmp_path) -> None:
    """Algorithm 7.5 through accelerate: the same closed loops as the Python filter."""
    from balustrade.codegen import CApproximatePCBFFilter
    from balustrade.codegen.runtime import mirror_c_retries
    from balustrade.examples.codegen import pendulum_approximate_filter

    py = pendulum_approximate_filter()
    py.decrease.compiled = mirror_c_retries(py.decrease.compiled)
    py.filter = mirror_c_retries(py.filter)
    c = accelerate(py, build_dir=tmp_path)
    assert isinstance(c, CApproximatePCBFFilter)
    for x0 in ([0.3, 0.5], [0.45, -1.2]):
        py.reset()
        c.reset()
        t1 = simulate(SYS, py, x0, 30, proposal=lambda k, x: 3.5 * np.sin(0.4 * k))
        t2 = simulate(SYS, c, x0, 30, proposal=lambda k, x: 3.5 * np.sin(0.4 * k))
        assert np.abs(t1.states - t2.states).max() <= 1e-6
        assert t1.statuses == t2.statuses and t1.fallbacks == t2.fallbacks
