"""The continuous-time plant: exact for linear systems (against the ZOH discretization by
the matrix exponential), convergent for the nonlinear pendulum, usable in simulate()."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from scipy.linalg import expm

from balustrade.control import StepInfo, simulate
from balustrade.control.plant import ContinuousPlant
from balustrade.dsl import LinearSystem
from balustrade.errors import BalustradeError

AC = np.array([[0.0, 1.0], [-2.0, -0.5]])
BC = np.array([[0.0], [1.0]])
EC = np.array([[0.1], [0.0]])
DT = 0.1


def zoh(dt: float = DT) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``expm([[A, B, E], [0, 0, 0]] dt)``: the exact sampled-data model."""
    M = np.zeros((4, 4))
    M[:2, :2], M[:2, 2:3], M[:2, 3:4] = AC, BC, EC
    Phi = expm(M * dt)
    return Phi[:2, :2], Phi[:2, 2:3], Phi[:2, 3:4]


def linear_plant(**kw) -> ContinuousPlant:
    return ContinuousPlant(lambda x, u, w: ca.mtimes(AC, x) + ca.mtimes(BC, u)
                           + ca.mtimes(EC, w), nx=2, nu=1, nw=1, dt=DT, name="lin", **kw)


@pytest.mark.parametrize("kw", [{}, {"method": "RK45"}, {"method": "Radau"},
                                {"method": "rk4", "substeps": 50}])
def test_linear_plant_matches_exact_zoh(kw):
    plant = linear_plant(**kw)
    Ad, Bd, Ed = zoh()
    rng = np.random.default_rng(0)
    for _ in range(10):
        x, u, w = rng.normal(size=2) * 3, rng.normal(size=1), rng.normal(size=1)
        np.testing.assert_allclose(plant.step(x, u, w), Ad @ x + Bd @ u + Ed @ w,
                                   rtol=0, atol=1e-8)


def pendulum_rhs(x: ca.SX, u: ca.SX) -> ca.SX:
    """The nonlinear pendulum behind (7.10): ψ̈ = g/l sin ψ − c ψ̇ + 5 u."""
    return ca.vertcat(x[1], 9.81 / 1.3 * ca.sin(x[0]) - 1.0 * x[1] + 5.0 * u[0])


def test_pendulum_rk4_converges_at_fourth_order():
    exact = ContinuousPlant(pendulum_rhs, 2, 1, DT, method="DOP853", rtol=1e-13, atol=1e-14)
    x, u = np.array([0.4, -1.0]), np.array([2.0])
    ref = exact.step(x, u)
    errors = [np.max(np.abs(ContinuousPlant(pendulum_rhs, 2, 1, DT, method="rk4",
                                            substeps=m).step(x, u) - ref))
              for m in (1, 2, 4, 8, 16)]
    assert all(b < a for a, b in zip(errors, errors[1:])), errors
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all(orders > 3.5), orders
    assert errors[-1] < 1e-8
    # and RK45 with tight tolerances agrees with DOP853
    rk45 = ContinuousPlant(pendulum_rhs, 2, 1, DT, method="RK45")
    np.testing.assert_allclose(rk45.step(x, u), ref, atol=1e-9)


class _StateFeedback:
    def __init__(self, K: np.ndarray):
        self.K = K

    def step(self, x, u_p):
        return -self.K @ x, StepInfo(values={"norm_x": float(np.linalg.norm(x))})

    def reset(self):
        pass


def test_simulate_against_continuous_plant_equals_exact_discrete_model():
    K = np.array([[1.0, 0.8]])
    Ad, Bd, Ed = zoh()
    w = np.random.default_rng(1).normal(size=(30, 1))
    cont = simulate(linear_plant(), _StateFeedback(K), [1.0, 0.0], 30, disturbance=w)
    disc = simulate(LinearSystem(Ad, Bd, Ed), _StateFeedback(K), [1.0, 0.0], 30, disturbance=w)
    assert cont.stopped is None and cont.states.shape == (31, 2)
    np.testing.assert_allclose(cont.states, disc.states, atol=1e-8)


def test_discretize_gives_the_controller_a_model():
    plant = ContinuousPlant(pendulum_rhs, 2, 1, DT, method="DOP853", rtol=1e-13, atol=1e-14)
    model = plant.discretize("rk4", steps=20)
    x, u = np.array([0.2, 0.3]), np.array([-1.0])
    np.testing.assert_allclose(model.step(x, u), plant.step(x, u), atol=1e-9)
    coarse = plant.discretize("euler")
    assert np.max(np.abs(coarse.step(x, u) - plant.step(x, u))) > 1e-3  # model mismatch


def test_plant_parameters_and_errors():
    f = lambda x, u, w, th: ca.vertcat(x[1], -th[0] * x[0] + u[0])
    soft = ContinuousPlant(f, 2, 1, DT, ntheta=1, theta=[1.0])
    stiff = ContinuousPlant(f, 2, 1, DT, ntheta=1, theta=[4.0])
    x = np.array([1.0, 0.0])
    assert stiff.step(x, [0.0])[1] < soft.step(x, [0.0])[1] < 0
    with pytest.raises(BalustradeError, match="unknown integration method"):
        ContinuousPlant(f, 2, 1, DT, ntheta=1, method="euler")
    with pytest.raises(BalustradeError, match="dt"):
        ContinuousPlant(f, 2, 1, 0.0, ntheta=1)
    with pytest.raises(BalustradeError, match="plant must be"):
        simulate(np.eye(2), _StateFeedback(np.ones((1, 2))), [0.0, 0.0], 2)


def test_pcbf_filter_designed_on_the_euler_model_against_the_continuous_pendulum(pend):
    """The PCBF filter of Section 7.5 is designed on the Euler model (7.10); against the
    continuous nonlinear pendulum it still never fails or falls back and keeps ψ <= 0.5, but
    the model mismatch lets |ω| overshoot its bound 1.5 a little (≈ 0.056 here) — the kind
    of finding a continuous plant is for."""
    from balustrade.control import PCBFSafetyFilter

    ctl = PCBFSafetyFilter(pend.compiled["slack", "casadi"], pend.compiled["filter", "casadi"],
                           pend.U)
    plant = ContinuousPlant(pendulum_rhs, 2, 1, 0.1, name="pendulum_ct")
    runs = {}
    for name, p in (("model", pend.system), ("continuous", plant)):
        ctl.reset()
        runs[name] = trace = simulate(p, ctl, [0.0, 1.5], 60, proposal=2.0)
        assert trace.stopped is None and trace.n_fallbacks == 0
        assert np.max(trace.states[:, 0]) <= 0.5 + 1e-6
    assert np.max(np.abs(runs["model"].states[:, 1])) <= 1.5 + 1e-6
    overshoot = np.max(np.abs(runs["continuous"].states[:, 1])) - 1.5
    assert 1e-3 < overshoot < 0.1, overshoot
