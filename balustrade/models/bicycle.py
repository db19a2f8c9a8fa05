"""Kinematic bicycle for lane changing (thesis Section 8.2, SPEC §2.31).

``x = (p_y, ψ, v, δ)``, ``u = (Δδ, τ)``, Euler with ``T_s = 0.05`` s:
``p_y⁺ = p_y + T_s v sin ψ``, ``ψ⁺ = ψ + T_s (v/l) tan δ + w``, ``v⁺ = v + T_s τ``,
``δ⁺ = δ + Δδ`` (a per-step steering increment), ``|w| <= 0.5°`` per step, wheelbase
``l = 0.09`` m (SPEC [Default], as in §8.3). Constraints: ``|p_y| <= 0.2`` m about the target
lane centre, ``|ψ| <= 35°``, ``0.5 <= v <= 1.3`` m/s, ``|δ| <= 35°``, ``|Δδ| <= 17.5°``,
``|τ| <= 2`` m/s².

The robust PCBF ingredients around the operating point ``x_s = (0, 0, 1.1, 0)`` (error set,
terminal CBF :class:`ShiftedCBF`) are synthesized in :mod:`balustrade.examples.bicycle`:
a model imports only the language.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from balustrade.dsl.sets import Box
from balustrade.dsl.system import System
from balustrade.errors import moved_names

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

#: names that moved out of this module (issue #13): deprecated aliases (errors.moved_names)
__getattr__ = moved_names(__name__, {
    "bicycle_design": "balustrade.examples.bicycle",
})
