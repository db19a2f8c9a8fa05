"""Bad input that passed silently before Session 14 (audit A): each is now refused before any
solver runs with a BalustradeError naming the argument, or (runtime data of a closed loop)
handled by a recorded fallback, never a NaN input."""

from __future__ import annotations

import warnings

import casadi as ca
import numpy as np
import pytest

from balustrade import compile
from balustrade.control.approximate import ApproximatePCBFFilter, GridPCBFFilter
from balustrade.control.mpc import MPCController
from balustrade.control.multiobjective import MultiobjectivePCBFController
from balustrade.control.pcbf import PCBFSafetyFilter
from balustrade.control.regret import RegretController
from balustrade.control.robust import RobustPCBFSafetyFilter
from balustrade.design.rpi import ellipsoidal_rpi
from balustrade.dsl.layout import Layout
from balustrade.dsl.sets import Box
from balustrade.dsl.system import LinearSystem
from balustrade.errors import BalustradeError, EmptySetError, TighteningWarning
from balustrade.problems.mpc import cbf_filter_problem, mpc_problem
from balustrade.problems.pcbf import pcbf_filter_problem, pcbf_slack_problem
from balustrade.problems.regret import LTVSystem, build_operators

A = np.array([[1.0, 0.1], [0.0, 1.0]])
B = np.array([[0.0], [0.1]])
SYS = LinearSystem(A, B, name="double_integrator")
X = Box([-1.0, -1.0], [1.0, 1.0], name="X")
U = Box([-1.0], [1.0], name="U")
N = 3
DELTAS = 1e-3 * np.arange(N)


def h_f(x: ca.SX) -> ca.SX:
    return ca.sumsqr(x) - 0.1


# -- 1. tightenings Δ_i (SPEC §1.4: 0 = Δ_0 < Δ_1 < …) -------------------------------------------
@pytest.mark.parametrize("deltas, match", [
    ([0.1, 0.2, 0.3], "Δ_0 must be 0"),
    (0.01, "Δ_0 must be 0"),                       # a scalar is repeated: Δ_0 = 0.01
    ([0.0, 0.2, 0.1], r"must increase .* i = \[1\]"),
])
def test_deltas_that_break_the_pcbf_decrease_are_refused(deltas, match):
    for build in (pcbf_slack_problem, pcbf_filter_problem):
        with pytest.raises(BalustradeError, match=match):
            build(SYS, X, U, h_f, N, deltas)


def test_equal_deltas_warn_and_strict_ones_do_not():
    with pytest.warns(TighteningWarning, match=r"not strictly increasing .* i = \[0, 1\]"):
        pcbf_slack_problem(SYS, X, U, h_f, N, np.zeros(N))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        pcbf_slack_problem(SYS, X, U, h_f, N, DELTAS)
        pcbf_slack_problem(SYS, X, U, h_f, 1, 0.0)   # N = 1: Δ_0 = 0 alone is strict


# -- 2. the slacks ξ of the filter (2.23) are >= 0 ------------------------------------------------
@pytest.mark.parametrize("name", ["xi", "xi_N"])
def test_filter_refuses_negative_slacks_before_solving(name):
    c = compile(pcbf_filter_problem(SYS, X, U, h_f, N, DELTAS), "cvxpy")
    params = {"x0": [0.1, 0.0], "u_p": [0.0], "xi": np.zeros((4, N)), "xi_N": 0.0}
    assert c.solve(params).status == "optimal"   # the same call with ξ = 0 solves
    params[name] = np.full((4, N), -0.05) if name == "xi" else -0.05
    with pytest.raises(BalustradeError, match=rf"'{name}': must be >= 0"):
        c.solve(params)


def test_parameter_lower_bound_survives_the_manifest():
    """The C runtime packs with ``Layout.from_dict(manifest)``: the bound must travel."""
    ocp = pcbf_filter_problem(SYS, X, U, h_f, N, DELTAS)
    lay = Layout.from_dict(ocp.parameter_layout.to_dict(), "c", "parameter")
    vals = {"x0": [0.0, 0.0], "u_p": [0.0], "xi": np.zeros((4, N)), "xi_N": -1.0}
    with pytest.raises(BalustradeError, match="'xi_N': must be >= 0"):
        lay.pack(vals)
    vals["xi_N"] = 0.0
    assert np.array_equal(lay.pack(vals), ocp.pack_parameters(vals))


# -- 3. an RPI set too large for X ----------------------------------------------------------------
def test_rpi_set_too_large_for_X_is_named_at_the_design():
    Xw = Box([-1.0, -10.0], [1.0, 10.0], name="Xnarrow")
    Uw = Box([-10.0], [10.0], name="Uwide")
    small = ellipsoidal_rpi(A, B, Box([-0.01, -0.01], [0.01, 0.01], name="Wsmall"), Xw, Uw)
    assert np.all(small.tighten_state(Xw).h > 0)
    with pytest.raises(EmptySetError, match=r"W \(Wbig\) is too large for X \(Xnarrow\)"):
        ellipsoidal_rpi(A, B, Box([-5.0, -5.0], [5.0, 5.0], name="Wbig"), Xw, Uw)


# -- 4. the CBF decrease α of (2.20) is >= 0 ------------------------------------------------------
def test_cbf_filter_refuses_a_negative_constant_decrease():
    with pytest.raises(BalustradeError, match=r"decrease .* must lie in \[0, inf\), got -0.1"):
        cbf_filter_problem(SYS, U, h_f, -0.1)
    cbf_filter_problem(SYS, U, h_f, 0.0)


# -- 5. RegretController on a NaN state -----------------------------------------------------------
def _regret() -> RegretController:
    ops = build_operators(LTVSystem.create(A, B, 3))
    rng = np.random.default_rng(0)
    K = np.zeros((ops.m * (ops.T + 1), ops.n * (ops.T + 1)))
    for k in range(ops.T + 1):   # a random causal gain: u_k depends on x_0..x_k
        K[ops.u_blocks[k], : ops.x_blocks[k].stop] = rng.normal(size=(ops.m, ops.n * (k + 1)))
    return RegretController(ops, K)


def test_regret_controller_replaces_a_nan_state_by_its_prediction():
    ctl = _regret()
    x0, x1 = np.array([0.3, -0.2]), np.array([0.1, 0.4])
    u0, _ = ctl.step(x0)
    u1, info = ctl.step([np.nan, 0.0])
    assert (info.status, info.fallback) == ("non_finite_state", "nominal_prediction")
    xhat = A @ x0 + B @ u0   # independent: the nominal state with w_0 = 0
    K = ctl.K
    assert np.allclose(u1, K[ctl.ops.u_blocks[1], :4] @ np.concatenate([x0, xhat]))
    u2, info2 = ctl.step(x1)
    assert info2.fallback is None and np.all(np.isfinite(u2))   # the NaN does not persist
    assert np.allclose(u2, K[ctl.ops.u_blocks[2], :6] @ np.concatenate([x0, xhat, x1]))


# -- sweep: every cheap controller refuses wrong shapes and never returns a NaN input ----------
def _pcbf():
    with warnings.catch_warnings():
        return PCBFSafetyFilter.build(SYS, X, U, h_f, N, DELTAS, alpha_f=1e3, target="cvxpy")


def _mpc():
    ocp = mpc_problem(SYS, X, U, None, N, np.eye(2), np.eye(1), np.eye(2))
    return MPCController(compile(ocp, "cvxpy"))


def _tube(cls: type):
    """A Chapter 5/6 controller on the §5.6 system (2 states, 1 input) of ``unstable2d_tube``."""
    def build(t: dict):
        s, cbf = t["s"], t["cbf"]
        return cls.build(t["system"], s.X, s.U, cbf, cbf.policy, t["N"], s.deltas(), t["error"],
                         s.alpha_f, target="robust-sqp", slack_target="robust-sqp")
    return build


CONTROLLERS = {
    "RobustPCBFSafetyFilter": _tube(RobustPCBFSafetyFilter),
    "MultiobjectivePCBFController": _tube(MultiobjectivePCBFController),
    "PCBFSafetyFilter": _pcbf,
    "MPCController": _mpc,
    "ApproximatePCBFFilter": lambda: ApproximatePCBFFilter(SYS, U, h_f, target="fast-sqp"),
    "GridPCBFFilter": lambda: GridPCBFFilter(SYS, U, h_f, half_width=0.5, spacing=0.25),
    "RegretController": _regret,
}
GOOD_X, GOOD_U = [0.1, 0.0], [0.0]


@pytest.fixture(scope="module", params=list(CONTROLLERS))
def controller(request):
    build = CONTROLLERS[request.param]
    if request.param in ("RobustPCBFSafetyFilter", "MultiobjectivePCBFController"):
        return build(request.getfixturevalue("unstable2d_tube"))
    return build()


@pytest.mark.parametrize("x, u_p, arg", [
    ([0.1, 0.0, 0.0], GOOD_U, "x"),
    ([[0.1, 0.0]] * 2, GOOD_U, "x"),
    ("ab", GOOD_U, "x"),
    (GOOD_X, [0.0, 0.0], "u_p"),
    (GOOD_X, "a", "u_p"),
])
def test_step_refuses_wrong_shapes_naming_the_argument(controller, x, u_p, arg):
    with pytest.raises(BalustradeError, match=rf"step: {arg}\b"):   # names the argument
        controller.step(x, u_p)


@pytest.mark.parametrize("x, u_p", [([np.nan, 0.0], GOOD_U), ([np.inf, 0.0], GOOD_U),
                                    (GOOD_X, [np.nan])])
def test_step_on_non_finite_data_records_it_and_returns_a_finite_input(controller, x, u_p):
    u, info = controller.step(x, u_p)
    assert np.all(np.isfinite(u)) and np.shape(u) == (1,)
    if not np.all(np.isfinite(x)):
        assert info.status == "non_finite_state" and info.fallback is not None
    elif not isinstance(controller, (MPCController, RegretController)):   # these ignore u_p
        assert "non_finite_proposal" in info.status


def test_a_rounding_below_the_lower_bound_is_packed_as_the_bound():
    """A solver's optimal slack comes back at −4.2e-17 (review R3, session 14): packed as 0,
    not refused; −1e-6 is still refused."""
    from balustrade.dsl.ocp import OCP

    ocp = OCP(SYS, N, name="lb_tol")
    ocp.parameter("xi", 2, lb=0.0)
    packed = ocp.parameter_layout.pack({"xi": np.array([-4.2e-17, 1.0])})
    assert packed[0] == 0.0 and packed[1] == 1.0
    with pytest.raises(BalustradeError, match="xi"):
        ocp.parameter_layout.pack({"xi": np.array([-1e-6, 1.0])})
