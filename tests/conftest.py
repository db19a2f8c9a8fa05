"""Shared fixtures: the pendulum example of Section 7.5 compiled once per session."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from balustrade.backends import compile
from balustrade.design.terminal_cbf import synthesize_terminal_cbf
from balustrade.models.pendulum import pendulum, pendulum_setup
from balustrade.problems.pcbf import (
    extended_pcbf_problem,
    pcbf_filter_problem,
    pcbf_slack_problem,
)

warnings.filterwarnings("ignore", message="Solution may be inaccurate")


#: the target each backend's tests use (the closed-loop default on CasADi)
BACKEND_TARGETS = {"casadi": "fast-sqp", "cvxpy": "cvxpy"}


class Pendulum:
    """The pendulum model, sets, terminal CBF and the PCBF problems on both backends."""

    def __init__(self) -> None:
        self.system = pendulum()
        self.setup = pendulum_setup()
        s = self.setup
        self.X, self.U, self.N, self.deltas, self.alpha_f = s.X, s.U, s.N, s.deltas, s.alpha_f
        self.h_f = synthesize_terminal_cbf(self.system.A, self.system.B, s.X, s.U,
                                           delta_N=s.deltas[-1])
        args = (self.system, s.X, s.U, self.h_f, s.N, s.deltas)
        self.slack = pcbf_slack_problem(*args, alpha_f=s.alpha_f, slack_norm=1)
        self.filter = pcbf_filter_problem(*args)
        self.extended = extended_pcbf_problem(*args)
        self.compiled = {
            (name, backend): compile(ocp, target)
            for name, ocp in (("slack", self.slack), ("filter", self.filter),
                              ("extended", self.extended))
            for backend, target in BACKEND_TARGETS.items()
        }

    def h_pb(self, x: np.ndarray, backend: str = "casadi") -> float:
        sol = self.compiled["slack", backend].solve({"x0": x})
        assert sol.success, sol.summary()
        return sol.objective

    def h_bar(self, x: np.ndarray, backend: str = "casadi") -> float:
        sol = self.compiled["extended", backend].solve({"x0": x})
        assert sol.success, sol.summary()
        return sol.objective


@pytest.fixture(scope="session")
def pend() -> Pendulum:
    return Pendulum()


@pytest.fixture(scope="session")
def unstable2d_tube():
    """The §5.6 system (N = 10) with its ellipsoidal RPI error set, tightened sets, the terminal
    CBF on X ⊖ E and the robust slack problem (5.15) — shared by the robust and the
    multiobjective tests."""
    from balustrade.design.rpi import ellipsoidal_rpi
    from balustrade.design.terminal_cbf import terminal_cbf_with_domain
    from balustrade.models.unstable2d import unstable2d, unstable2d_setup
    from balustrade.problems.robust import robust_pcbf_slack_problem

    N = 10
    system, s = unstable2d(), unstable2d_setup(N)
    error = ellipsoidal_rpi(system.A, system.B, s.W, s.X, s.U)
    X_E, U_E = error.tighten_state(s.X), error.tighten_input(s.U)
    cbf = terminal_cbf_with_domain(system.A, system.B, X_E, U_E, s.deltas()[-1], level=1.0)
    slack = robust_pcbf_slack_problem(system, s.X, s.U, cbf, N, s.deltas(), error, s.alpha_f)
    return {"system": system, "s": s, "error": error, "cbf": cbf, "X_E": X_E, "U_E": U_E,
            "slack": slack, "N": N}


@pytest.fixture(scope="session")
def rapsf_toy():
    """The 2-state toy of the Chapter 4 tests: x⁺ = A(θ)x + Bu + w with θ ∈ [0.5, 1.5] ×
    [0, 0.5] acting on the velocity row, |w| <= 0.004, X = [−2, 2]², U = [−3, 3]; the robust
    gain (contraction 0.95) and a λ-contractive tube shape 𝕏₀ (one design per session)."""
    from types import SimpleNamespace

    from balustrade.design.rapsf import contractive_polytope, robust_gain
    from balustrade.dsl.sets import Box
    from balustrade.dsl.system_parametric import ParametricLinearSystem
    from balustrade.problems.rapsf import joint_constraints

    sys_ = ParametricLinearSystem(np.array([[1.0, 0.1], [0.0, 1.0]]),
                                  [np.array([[0.0, 0.0], [-0.1, 0.0]]),
                                   np.array([[0.0, 0.0], [0.0, -0.1]])],
                                  np.array([[0.0], [0.1]]), None, name="toy")
    Theta0 = Box([0.5, 0.0], [1.5, 0.5], name="Theta0")
    V = Theta0.vertices()
    W = Box.symmetric(0.004, 2, name="W")
    F, G = joint_constraints(Box.symmetric(2.0, 2), Box.symmetric(3.0, 1))
    K = robust_gain(sys_, V, contraction=0.95)
    X0 = contractive_polytope(sys_, K, V, W, F, G)
    return SimpleNamespace(sys=sys_, Theta0=Theta0, V=V, W=W, F=F, G=G, K=K, X0=X0)
