"""Damped inverted pendulum (7.10), thesis Section 7.5.

``x = (ψ, ω)`` (angle, angular rate), ``x⁺ = A x + B u`` with
``A = [[1, T_s], [T_s g / l, 1 − T_s c]]``, ``B = [0, 5 T_s]ᵀ``, ``T_s = 0.1``, ``c = 1``,
``l = 1.3``, ``g = 9.81``; ``|ψ| <= 0.5``, ``|ω| <= 1.5``, ``|u| <= 3``; PCBF settings
``N = 10``, ``Δ_i = i·10⁻³``, ``α_f = 10⁶`` (SPEC §3.5).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from balustrade.dsl.sets import Box
from balustrade.dsl.system import LinearSystem

TS, DAMPING, LENGTH, GRAVITY = 0.1, 1.0, 1.3, 9.81


def pendulum(ts: float = TS, damping: float = DAMPING, length: float = LENGTH,
             gravity: float = GRAVITY) -> LinearSystem:
    """The linear pendulum model (7.10)."""
    A = np.array([[1.0, ts], [ts * gravity / length, 1.0 - ts * damping]])
    B = np.array([[0.0], [5.0 * ts]])
    return LinearSystem(A, B, name="pendulum")


@dataclass(frozen=True)
class PendulumSetup:
    """Constraint sets and PCBF settings of Section 7.5."""

    X: Box
    U: Box
    N: int = 10
    delta_step: float = 1e-3
    alpha_f: float = 1e6

    @property
    def deltas(self) -> np.ndarray:
        """``Δ_i = i · 10⁻³`` for ``i ∈ I[0, N−1]``."""
        return self.delta_step * np.arange(self.N)


def pendulum_setup() -> PendulumSetup:
    return PendulumSetup(X=Box.symmetric([0.5, 1.5], name="X"),
                         U=Box.symmetric([3.0], name="U"))
