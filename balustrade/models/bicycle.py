"""Kinematic bicycle for lane changing (thesis Section 8.2, SPEC §2.31).

``x = (p_y, ψ, v, δ)``, ``u = (Δδ, τ)``, Euler with ``T_s = 0.05`` s:
``p_y⁺ = p_y + T_s v sin ψ``, ``ψ⁺ = ψ + T_s (v/l) tan δ + w``, ``v⁺ = v + T_s τ``,
``δ⁺ = δ + Δδ`` (a per-step steering increment), ``|w| <= 0.5°`` per step, wheelbase
``l = 0.09`` m (SPEC [Default], as in §8.3). Constraints: ``|p_y| <= 0.2`` m about the target
lane centre, ``|ψ| <= 35°``, ``0.5 <= v <= 1.3`` m/s, ``|δ| <= 35°``, ``|Δδ| <= 17.5°``,
``|τ| <= 2`` m/s².

:func:`bicycle_design` builds the robust PCBF ingredients around the operating point
``x_s = (0, 0, 1.1, 0)``: an error set and feedback from the ellipsoidal RPI SDP on the
linearization (a *user-given* ``E`` and ``κ`` for the nonlinear model — designing incremental
Lyapunov functions over all Jacobians is out of scope; :func:`nonlinear_rpi_margin` checks the
property by sampling) and a terminal CBF ``h_f(x) = (x − x_s)ᵀP(x − x_s) − 1`` with
``π_f(x) = K_f (x − x_s)`` from the SDP (6.17) on the linearization.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from balustrade.dsl.error_sets import ErrorSet
from balustrade.dsl.sets import Box, Polytope
from balustrade.dsl.system import System
from balustrade.problems.robust import terminal_cbf_with_domain
from balustrade.problems.rpi import ellipsoidal_rpi

TS, WHEELBASE, V_S = 0.05, 0.09, 1.1
DEG = np.pi / 180.0


def bicycle(ts: float = TS, wheelbase: float = WHEELBASE) -> System:
    def f(x: ca.SX, u: ca.SX, w: ca.SX) -> ca.SX:
        return ca.vertcat(x[0] + ts * x[2] * ca.sin(x[1]),
                          x[1] + ts * x[2] / wheelbase * ca.tan(x[3]) + w[0],
                          x[2] + ts * u[1],
                          x[3] + u[0])

    return System(f, nx=4, nu=2, nw=1, name="kinematic_bicycle")


def bicycle_sets() -> tuple[Box, Box, Box]:
    X = Box([-0.2, -35 * DEG, 0.5, -35 * DEG], [0.2, 35 * DEG, 1.3, 35 * DEG], name="X_lane")
    U = Box([-17.5 * DEG, -2.0], [17.5 * DEG, 2.0], name="U_bicycle")
    W = Box([-0.5 * DEG], [0.5 * DEG], name="W_heading")
    return X, U, W


@dataclass
class ShiftedCBF:
    """``h_f(x) = (x − x_s)ᵀP(x − x_s) − 1`` and ``π_f(x) = K(x − x_s)`` (``u_s = 0``)."""

    P: np.ndarray
    K: np.ndarray
    x_s: np.ndarray
    gamma_f: float

    def __call__(self, x: object) -> object:
        if isinstance(x, (ca.SX, ca.MX, ca.DM)):
            d = x - ca.DM(self.x_s)
            return ca.mtimes([d.T, ca.DM(self.P), d]) - 1
        d = np.asarray(x, dtype=float).reshape(-1) - self.x_s
        return float(d @ self.P @ d - 1.0)

    def policy(self, x: np.ndarray) -> np.ndarray:
        return self.K @ (np.asarray(x, dtype=float).reshape(-1) - self.x_s)


@dataclass
class BicycleDesign:
    system: System
    X: Box
    U: Box
    W: Box
    error: ErrorSet
    cbf: ShiftedCBF
    N: int
    deltas: np.ndarray
    alpha_f: float = 1e6


def bicycle_design(N: int = 20, delta_step: float = 1e-4) -> BicycleDesign:
    system = bicycle()
    X, U, W = bicycle_sets()
    x_s = np.array([0.0, 0.0, V_S, 0.0])
    A, B = system.jacobians(x_s, np.zeros(2))
    G = np.array([[0.0], [1.0], [0.0], [0.0]])
    Xs = Polytope(X.H, X.h - X.H @ x_s, name="X_lane-x_s")
    error = ellipsoidal_rpi(A, B, W, Xs, U, G=G, name="E_bicycle")
    X_E, U_E = error.tighten_state(Xs), error.tighten_input(U)
    deltas = delta_step * np.arange(N)
    cbf = terminal_cbf_with_domain(A, B, X_E, U_E, deltas[-1], level=1.0)
    return BicycleDesign(system, X, U, W, error, ShiftedCBF(cbf.P, cbf.K, x_s, cbf.gamma_f),
                         N, deltas)


def nonlinear_rpi_margin(design: BicycleDesign, samples: int = 2000, seed: int = 0) -> float:
    """Sampled ``max c_E(e⁺)`` of the nominal-vs-true error ``e⁺ = f(z + e, v + Ke, w) −
    f(z, v, 0)`` over ``z ∈ X``, ``v ∈ U ⊖ KE``, ``e ∈ ∂E``, ``w ∈ W`` (<= 0: no counterexample)."""
    rng = np.random.default_rng(seed)
    d = design
    E, K = d.error.E, d.error.K
    U_E = d.error.tighten_input(d.U)
    f = d.system.function
    worst = -np.inf
    zs = d.X.sample(samples, rng)
    vs = U_E.sample(samples, rng)
    es = E.sample(samples, rng)
    es /= np.sqrt(np.einsum("ij,jk,ik->i", es, E.P, es))[:, None]
    ws = d.W.sample(samples, rng)
    for z, v, e, w in zip(zs, vs, es, ws):
        e_next = np.asarray(f(z + e, v + K @ e, w, np.zeros(0))).reshape(-1) - \
            np.asarray(f(z, v, np.zeros(1), np.zeros(0))).reshape(-1)
        worst = max(worst, float(e_next @ E.P @ e_next - 1.0))
    return worst
