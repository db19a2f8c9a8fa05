"""Cart-pole: a cart on a track with an inverted pole (issue #14, the nonlinear PCBF case).

State ``x = (p, θ, ṗ, θ̇)``: cart position [m], pole angle from upright [rad], their rates;
input ``u = F``: horizontal force on the cart [N]. Point-mass pole of mass ``m`` at distance
``l`` from the frictionless pivot, cart mass ``M``. The Euler–Lagrange equations of
``L = ½(M+m)ṗ² + m l ṗ θ̇ cos θ + ½ m l² θ̇² − m g l cos θ`` give

``p̈ = (F + m sin θ (l θ̇² − g cos θ)) / (M + m sin² θ)``,
``θ̈ = (g sin θ − p̈ cos θ) / l``,

discretized by one classic RK4 step per sample ``T_s`` (:meth:`System.from_continuous`).
With ``F = 0`` the energy ``E = ½(M+m)ṗ² + m l ṗ θ̇ cos θ + ½ m l² θ̇² + m g l cos θ`` is
conserved (:func:`cartpole_energy`, used by the tests).

Constants (chosen here, not from the thesis): ``M = 1`` kg, ``m = 0.1`` kg, ``l = 0.5`` m,
``g = 9.81`` m/s², ``T_s = 0.05`` s. Constraints: track ``|p| <= 1`` m, ``|θ| <= 0.35`` rad
(20°), ``|ṗ| <= 2`` m/s, ``|θ̇| <= 3`` rad/s; input ``|F| <= 10`` N. The upright equilibrium
is open-loop unstable (time constant ``√(l M / (g (M+m)))`` ≈ 0.21 s); the PCBF design
(:mod:`balustrade.examples.cartpole`) uses ``N = 20`` (1 s), ``Δ_i = i·10⁻⁴``,
``α_f = 10⁶``.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from balustrade.dsl.sets import Box
from balustrade.dsl.system import System

TS, CART_MASS, POLE_MASS, LENGTH, GRAVITY = 0.05, 1.0, 0.1, 0.5, 9.81


def cartpole_ct(M: float = CART_MASS, m: float = POLE_MASS, length: float = LENGTH,
                g: float = GRAVITY):
    """The continuous-time right-hand side ``ẋ = f_ct(x, u)`` (module docstring)."""

    def f(x: ca.SX, u: ca.SX) -> ca.SX:
        th, pd, thd = x[1], x[2], x[3]
        s, c = ca.sin(th), ca.cos(th)
        pdd = (u[0] + m * s * (length * thd ** 2 - g * c)) / (M + m * s ** 2)
        thdd = (g * s - pdd * c) / length
        return ca.vertcat(pd, thd, pdd, thdd)

    return f


def cartpole(ts: float = TS, M: float = CART_MASS, m: float = POLE_MASS,
             length: float = LENGTH, g: float = GRAVITY) -> System:
    """The cart-pole discretized by one RK4 step of length ``ts``."""
    return System.from_continuous(cartpole_ct(M, m, length, g), nx=4, nu=1, dt=ts,
                                  method="rk4", name="cartpole")


def cartpole_energy(x: np.ndarray, M: float = CART_MASS, m: float = POLE_MASS,
                    length: float = LENGTH, g: float = GRAVITY) -> float:
    """Total mechanical energy (conserved for ``F = 0``)."""
    _, th, pd, thd = np.asarray(x, dtype=float).reshape(-1)
    return float(0.5 * (M + m) * pd ** 2 + m * length * pd * thd * np.cos(th)
                 + 0.5 * m * length ** 2 * thd ** 2 + m * g * length * np.cos(th))


@dataclass(frozen=True)
class CartpoleSetup:
    """Constraint sets and PCBF settings (module docstring)."""

    X: Box
    U: Box
    N: int = 20
    delta_step: float = 1e-4
    alpha_f: float = 1e6

    @property
    def deltas(self) -> np.ndarray:
        """``Δ_i = i · delta_step`` for ``i ∈ I[0, N−1]``."""
        return self.delta_step * np.arange(self.N)


def cartpole_setup(N: int = 20) -> CartpoleSetup:
    return CartpoleSetup(X=Box.symmetric([1.0, 0.35, 2.0, 3.0], name="X_cartpole"),
                         U=Box.symmetric([10.0], name="U_cartpole"), N=N)
