"""The kinematic bicycle example (thesis Section 8.2, SPEC §2.31): robust PCBF ingredients.

:func:`bicycle_design` builds them around the operating point ``x_s = (0, 0, 1.1, 0)``: an
error set and feedback from the ellipsoidal RPI SDP on the linearization (a *user-given*
``E`` and ``κ`` for the nonlinear model — designing incremental Lyapunov functions over all
Jacobians is out of scope; :func:`nonlinear_rpi_margin` checks the property by sampling) and
a terminal CBF ``h_f(x) = (x − x_s)ᵀP(x − x_s) − 1`` with ``π_f(x) = K_f (x − x_s)`` from
the SDP (6.17) on the linearization. The model itself is :mod:`balustrade.models.bicycle`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from balustrade.design.rpi import ellipsoidal_rpi
from balustrade.design.terminal_cbf import terminal_cbf_with_domain
from balustrade.dsl.error_sets import ErrorSet
from balustrade.dsl.sets import Box, Polytope
from balustrade.dsl.system import System
from balustrade.models.bicycle import V_S, ShiftedCBF, bicycle, bicycle_sets


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
