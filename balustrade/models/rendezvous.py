"""Spacecraft rendezvous with Clohessy–Wiltshire–Hill dynamics (thesis Section 6.5, SPEC §3.4).

Continuous time, ``x = (p_x, p_y, p_z, v_x, v_y, v_z)``:
``p̈_x = 3n²p_x + 2n ṗ_y + u_x``, ``p̈_y = −2n ṗ_x + u_y``, ``p̈_z = −n² p_z + u_z``.
The thesis gives neither the sampling time nor the mean motion ("arbitrary units"). We use
**normalized units: exact zero-order-hold discretization with ``T_s = 1`` and mean motion
``n = 0.01``** (issue 3; this overrides SPEC §3.4's ``n₀ = 1``, ``T_s = 0.1`` default, under
which the orbital coupling would dominate the manoeuvre). The disturbance acts on the velocities
only: ``x⁺ = A x + B u + G w`` with ``G = [0; I₃]``, ``‖w‖∞ <= 0.5``.

Sets and settings: target set ``X = {|p_j| <= 10, |v_j| <= 20}``, ``U = {‖u‖∞ <= 20}``,
``N = 200``, ``T = 400``, ``Δ_i = i·10⁻³``, ``α_f = 10⁶``, ``x₀ = (100, 100, 100, 0, 0, 0)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from balustrade.dsl.sets import Box
from balustrade.dsl.system import LinearSystem
from balustrade.models.setups import RobustPCBFSetup

MEAN_MOTION = 0.01
TS = 1.0


def cwh_matrices(n: float = MEAN_MOTION, ts: float = TS) -> tuple[np.ndarray, np.ndarray]:
    """Exact ZOH discretization of the CWH equations: ``expm([[A_c, B_c], [0, 0]] T_s)``."""
    Ac = np.zeros((6, 6))
    Ac[:3, 3:] = np.eye(3)
    Ac[3, 0], Ac[3, 4] = 3 * n ** 2, 2 * n
    Ac[4, 3] = -2 * n
    Ac[5, 2] = -n ** 2
    Bc = np.vstack([np.zeros((3, 3)), np.eye(3)])
    M = np.zeros((9, 9))
    M[:6, :6], M[:6, 6:] = Ac, Bc
    E = scipy.linalg.expm(M * ts)
    return E[:6, :6], E[:6, 6:]


def rendezvous(n: float = MEAN_MOTION, ts: float = TS) -> LinearSystem:
    A, B = cwh_matrices(n, ts)
    G = np.vstack([np.zeros((3, 3)), np.eye(3)])
    return LinearSystem(A, B, G, name="cwh_rendezvous")


@dataclass(frozen=True)
class RendezvousSetup(RobustPCBFSetup):
    """Sets and PCBF settings of Section 6.6: N = 200, task length T = 400 steps,
    ``Δ_i = i · 10⁻³`` (SPEC [Gap]: the printed constant ``10⁻³`` is not increasing)."""

    N: int = 200
    delta_step: float = 1e-3
    T: int = 400
    x0: tuple[float, ...] = (100.0, 100.0, 100.0, 0.0, 0.0, 0.0)


def rendezvous_setup(N: int = 200, T: int = 400) -> RendezvousSetup:
    return RendezvousSetup(X=Box.symmetric([10.0] * 3 + [20.0] * 3, name="X"),
                           U=Box.symmetric([20.0] * 3, name="U"),
                           W=Box.symmetric([0.5] * 3, name="W"), N=N, T=T)
