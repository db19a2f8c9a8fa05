"""Kinematic miniature race car among disc obstacles (thesis Section 8.3, model (8.1),
SPEC §2.32 and §3.7).

``x = (p_x, p_y, ψ, v, δ)``, ``u = (τ, Δδ)``, Euler with ``T_s = 0.02`` s and wheelbase
``l = 0.09`` m::

    p_x⁺ = p_x + T_s v cos ψ      ψ⁺ = ψ + T_s (v / l) tan δ      δ⁺ = δ + T_s Δδ
    p_y⁺ = p_y + T_s v sin ψ      v⁺ = v + T_s τ

Inputs ``−5 <= τ <= 2``, ``−2.8 <= Δδ <= 2.8``; state constraints ``|δ| <= 0.75`` and nine
disks ``c_{x,i}(x) = r² − (p_x − o_{x,i})² − (p_y − o_{y,i})² <= 0`` ([Default] r = 0.15 on a
3 × 3 grid with 0.8 m spacing centred at the origin). The other states are unconstrained:
the large boxes SPEC §2.32 allows for compactness of ``X(ξ)`` are left out of ``c_x`` (they
would never be active and would add 4 rows × N slacks to (2.24)); the sampling domain
:attr:`ObstacleSetup.domain` plays their role for the data.

The obstacle layout, the δ box and the input box are invariant under the 8 symmetries of
the square (rotations by multiples of 90° and reflections), and (8.1) is equivariant under
them: :func:`symmetries` maps states so that ``h(g x) = h(x)`` for the PCBF of this model
(used to augment sampled data, exact).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from balustrade._checks import as_float_array, as_scalar
from balustrade.dsl.sets import Box
from balustrade.dsl.sets_function import FunctionSet
from balustrade.dsl.system import System
from balustrade.errors import ShapeError

TS, WHEELBASE = 0.02, 0.09
RADIUS, SPACING = 0.15, 0.8
DELTA_MAX = 0.75
ARENA = ((-2.0, 2.0), (-1.5, 1.5))


def obstacle_car(ts: float = TS, wheelbase: float = WHEELBASE) -> System:
    """Model (8.1); ``ts`` and ``wheelbase`` must be positive (a BalustradeError names them)."""
    ts = as_scalar(ts, "obstacle_car: ts", low=0.0, low_open=True)
    wheelbase = as_scalar(wheelbase, "obstacle_car: wheelbase", low=0.0, low_open=True)

    def f(x: ca.SX, u: ca.SX, w: ca.SX) -> ca.SX:
        return ca.vertcat(x[0] + ts * x[3] * ca.cos(x[2]),
                          x[1] + ts * x[3] * ca.sin(x[2]),
                          x[2] + ts * x[3] / wheelbase * ca.tan(x[4]),
                          x[3] + ts * u[0],
                          x[4] + ts * u[1])

    return System(f, nx=5, nu=2, name="obstacle_car")


def grid_obstacles(spacing: float = SPACING, radius: float = RADIUS) -> np.ndarray:
    """Rows ``(o_x, o_y, r)`` of the 3 × 3 grid of disks centred at the origin."""
    c = spacing * np.array([-1.0, 0.0, 1.0])
    return np.array([[ox, oy, radius] for ox in c for oy in c])


def _obstacle_rows(obstacles: object, block: str) -> np.ndarray:
    """``obstacles`` as an ``(m, 3)`` array of rows ``(o_x, o_y, r)``, finite, ``r >= 0``."""
    obs = as_float_array(obstacles, block)
    if obs.ndim != 2 or obs.shape[1] != 3:
        raise ShapeError(block, "(m, 3) rows (o_x, o_y, r)", obs.shape)
    if not np.all(np.isfinite(obs)) or np.any(obs[:, 2] < 0):
        raise ShapeError(block, "finite rows with a radius r >= 0", obs.tolist())
    return obs


def constraint_set(obstacles: np.ndarray, delta_max: float = DELTA_MAX) -> FunctionSet:
    """``X = {x : c_x(x) <= 0}``: one row per disc, then ``δ − δ̄`` and ``−δ − δ̄``."""
    obs = _obstacle_rows(obstacles, "constraint_set: obstacles")

    def c(x: ca.SX) -> ca.SX:
        disks = [o[2] ** 2 - (x[0] - o[0]) ** 2 - (x[1] - o[1]) ** 2 for o in obs]
        return ca.vertcat(*disks, x[4] - delta_max, -x[4] - delta_max)

    return FunctionSet(c, 5, name="X_obstacles")


@dataclass(frozen=True)
class ObstacleSetup:
    """Constraints, PCBF settings (Δ_j = j·1e-4, N = 50, hard terminal ``v_N = 0``) and the
    sampling domain of Section 8.3."""

    obstacles: np.ndarray = field(default_factory=grid_obstacles)
    U: Box = field(default_factory=lambda: Box([-5.0, -2.8], [2.0, 2.8], name="U_car"))
    N: int = 50
    delta_step: float = 1e-4
    delta_max: float = DELTA_MAX
    #: sampling domain: the arena, |ψ| <= π + 0.5 (ψ is not wrapped in the closed loop),
    #: 0 <= v <= 4 (a stop within N T_s = 1 s needs v <= 5), |δ| <= 0.75
    domain: Box = field(default_factory=lambda: Box(
        [ARENA[0][0], ARENA[1][0], -np.pi - 0.5, 0.0, -DELTA_MAX],
        [ARENA[0][1], ARENA[1][1], np.pi + 0.5, 4.0, DELTA_MAX], name="D_obstacles"))

    @property
    def X(self) -> FunctionSet:
        return constraint_set(self.obstacles, self.delta_max)

    @property
    def deltas(self) -> np.ndarray:
        """``Δ_j = j · 10⁻⁴`` for ``j ∈ I[0, N−1]``."""
        return self.delta_step * np.arange(self.N)

    @property
    def delta_N(self) -> float:
        return self.delta_step * self.N

    @property
    def n_rows(self) -> int:
        return len(self.obstacles) + 2


def obstacle_setup() -> ObstacleSetup:
    return ObstacleSetup()


def signed_distance(positions: np.ndarray, obstacles: np.ndarray | None = None) -> np.ndarray:
    """Signed distance ``‖p − o_i‖ − r_i`` of each position (rows ``(p_x, p_y, …)``) to each
    disc: shape ``(n, n_obstacles)``, negative inside a disc. ``positions``: at least two
    columns (a single ``(p_x, p_y, …)`` row may be 1-D); ``obstacles``: ``(m, 3)`` rows.
    Wrong shapes raise a BalustradeError: an ``(n, 1)`` array used to broadcast its one
    column as both coordinates and return distances of the wrong points (audit D,
    session 15). NaN positions give NaN distances."""
    obs = grid_obstacles() if obstacles is None else \
        _obstacle_rows(obstacles, "signed_distance: obstacles")
    P = as_float_array(positions, "signed_distance: positions")
    P = P.reshape(1, -1) if P.ndim == 1 else P
    if P.ndim != 2 or P.shape[1] < 2:
        raise ShapeError("signed_distance: positions", "(n, >= 2) rows (p_x, p_y, ...)",
                         P.shape)
    P = P[:, :2]
    return np.linalg.norm(P[:, None, :] - obs[None, :, :2], axis=2) - obs[None, :, 2]


def symmetries(X: np.ndarray) -> np.ndarray:
    """The 8 images ``g x`` of every row of ``X`` under the symmetries of the square
    (``g`` acts on ``(p_x, p_y)`` as a rotation/reflection ``R``, on the heading as the
    matching map of angles, flips δ for reflections; ``v`` is unchanged). The identity
    images are the rows themselves; the headings of the other images are wrapped to
    ``(−π, π]`` (``h`` is 2π-periodic in ψ). Returns ``(8 n, 5)``, the identity first.
    ``X``: ``(n, 5)`` rows (one state may be 1-D), else a BalustradeError."""
    X = as_float_array(X, "symmetries: X")
    X = X.reshape(1, -1) if X.ndim == 1 else X
    if X.ndim != 2 or X.shape[1] != 5:
        raise ShapeError("symmetries: X", "(n, 5) states (p_x, p_y, psi, v, delta)", X.shape)
    px, py, psi, v, d = X.T
    out = []
    for k in range(4):  # rotations by k·90°
        a = k * np.pi / 2
        c, s = np.cos(a), np.sin(a)
        for reflect in (False, True):
            x0, y0, p0, d0 = (px, -py, -psi, -d) if reflect else (px, py, psi, d)
            x1, y1 = np.round(c, 12) * x0 - np.round(s, 12) * y0, \
                np.round(s, 12) * x0 + np.round(c, 12) * y0
            p1 = p0 + a
            if k or reflect:
                p1 = np.arctan2(np.sin(p1), np.cos(p1))
            out.append(np.column_stack([x1, y1, p1, v, d0]))
    return np.vstack(out)


__all__ = ["ARENA", "ObstacleSetup", "constraint_set", "grid_obstacles", "obstacle_car",
           "obstacle_setup", "signed_distance", "symmetries"]
