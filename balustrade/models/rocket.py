"""Planar 3-DoF rocket linearized at hover (thesis Section 3.8).

The thesis omits the model; this follows the authors' public code as quoted in issue 4
(it overrides the [Default] rocket of SPEC 3.1): states (y, z, v_y, v_z, θ, ω), inputs
(u_y, u_z) = thrust deviation from m·g, forward-Euler discretization with T_s = 0.1,
m = l = J = 1, g = 9.81.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

G_ACC = 9.81


@dataclass(frozen=True)
class RocketRegretSetup:
    """Everything the regret example needs: dynamics, weights, sets, x₀, horizon."""

    Ts: float = 0.1
    m: float = 1.0
    l: float = 1.0
    J: float = 1.0
    T: int = 25
    x0: np.ndarray = field(default_factory=lambda: np.array([0.7, 0.7, 0.0, 0.0, 0.0, 0.0]))
    pos_vel_bound: float = 5.0
    angle_bound: float = np.deg2rad(45.0)
    cone_half_angle: float = np.deg2rad(30.0)
    box: np.ndarray = field(default_factory=lambda: np.array(
        [0.03, 0.03, 0.03, 0.03, np.deg2rad(0.7), np.deg2rad(0.7)]))

    @property
    def A(self) -> np.ndarray:
        A = np.eye(6)
        A[0, 2] = A[1, 3] = A[4, 5] = self.Ts
        return A

    @property
    def B(self) -> np.ndarray:
        B = np.zeros((6, 2))
        B[2, 0] = B[3, 1] = self.Ts / self.m
        B[5, 0] = self.Ts * self.l / self.J
        return B

    @property
    def P(self) -> np.ndarray:
        """Ellipsoid {wᵀPw ≤ 1} through the vertices of the box |w_i| ≤ b_i: P = diag(1/(6b_i²))."""
        return np.diag(1.0 / (6.0 * self.box**2))

    @property
    def omega(self) -> float:
        """Energy bound ω = T/λ_min(P) covering every pointwise-bounded sequence (3.33)."""
        return self.T / float(np.min(np.linalg.eigvalsh(self.P)))

    def state_halfspaces(self) -> tuple[np.ndarray, np.ndarray]:
        """|y|, |z|, |v_y|, |v_z| ≤ 5 and |θ|, |ω| ≤ 45° as A_x x ≤ b_x."""
        bounds = np.array([self.pos_vel_bound] * 4 + [self.angle_bound] * 2)
        return np.vstack([np.eye(6), -np.eye(6)]), np.concatenate([bounds, bounds])

    def input_halfspaces(self) -> tuple[np.ndarray, np.ndarray]:
        """Thrust cone |u_y| ≤ tan30°(u_z + mg) and −0.5mg ≤ u_z ≤ 2mg as A_u u ≤ b_u."""
        t, mg = np.tan(self.cone_half_angle), self.m * G_ACC
        Au = np.array([[1.0, -t], [-1.0, -t], [0.0, -1.0], [0.0, 1.0]])
        bu = np.array([t * mg, t * mg, 0.5 * mg, 2.0 * mg])
        return Au, bu
