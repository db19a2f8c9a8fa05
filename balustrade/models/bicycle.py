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

**Jacobian structure** (:func:`jacobian_ldi`). ``∂f/∂u = B`` is constant and

``∂f/∂x = I + a_1 e_1e_2ᵀ + a_2 e_1e_3ᵀ + a_3 e_2e_3ᵀ + a_4 e_2e_4ᵀ`` with
``a = (T_s v cos ψ, T_s sin ψ, T_s tan δ / l, T_s v / (l cos² δ))``:

affine in four nonlinear functions of ``(ψ, v, δ)`` only (not of ``p_y``, ``u`` or ``w``).
On a box of ``(ψ, v, δ)`` with ``|ψ|, |δ| < 90°`` each ``a_k`` ranges over an interval
computed exactly (monotonicity of sin and tan, products of intervals of one sign for
``v cos ψ`` and ``v / cos² δ``), so every Jacobian on the box lies in the convex hull of
the 16 matrices at the corners of the interval box of ``a`` (a polytopic LDI).
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from balustrade._checks import as_scalar, as_vector
from balustrade.dsl.policies import AffinePolicy
from balustrade.dsl.sets import Box
from balustrade.dsl.system import System
from balustrade.errors import BalustradeError, moved_names

TS, WHEELBASE, V_S = 0.05, 0.09, 1.1
DEG = np.pi / 180.0


def _positive(ts: object, wheelbase: object, block: str) -> tuple[float, float]:
    """``T_s`` and ``l``, both finite and positive (a BalustradeError names them)."""
    return (as_scalar(ts, f"{block}: ts", low=0.0, low_open=True),
            as_scalar(wheelbase, f"{block}: wheelbase", low=0.0, low_open=True))


def bicycle(ts: float = TS, wheelbase: float = WHEELBASE) -> System:
    """The kinematic bicycle of the module docstring (``ts``, ``wheelbase`` positive)."""
    ts, wheelbase = _positive(ts, wheelbase, "bicycle")

    def f(x: ca.SX, u: ca.SX, w: ca.SX) -> ca.SX:
        return ca.vertcat(x[0] + ts * x[2] * ca.sin(x[1]),
                          x[1] + ts * x[2] / wheelbase * ca.tan(x[3]) + w[0],
                          x[2] + ts * u[1],
                          x[3] + u[0])

    return System(f, nx=4, nu=2, nw=1, name="kinematic_bicycle")


def input_matrix(ts: float = TS) -> np.ndarray:
    """``∂f/∂u`` (constant): ``Δδ`` enters ``δ`` directly, ``τ`` enters ``v`` times ``T_s``."""
    return np.array([[0.0, 0.0], [0.0, 0.0], [0.0, ts], [1.0, 0.0]])


def _interval_product(a: tuple[float, float], b: tuple[float, float]) -> tuple[float, float]:
    corners = [a[0] * b[0], a[0] * b[1], a[1] * b[0], a[1] * b[1]]
    return min(corners), max(corners)


def _even_range(fn: object, lo: float, hi: float) -> tuple[float, float]:
    """Range of an even function increasing in ``|θ|`` on ``[lo, hi]`` (cos⁻², −cos)."""
    ends = [fn(lo), fn(hi)]
    return (fn(0.0) if lo <= 0.0 <= hi else min(ends)), max(ends)


def jacobian_ldi(lb: np.ndarray, ub: np.ndarray, ts: float = TS, wheelbase: float = WHEELBASE
                 ) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """``(A0, [E_1..E_4], intervals)`` with ``∂f/∂x = A0 + Σ_k a_k E_k`` and
    ``a_k ∈ [intervals[k, 0], intervals[k, 1]]`` for every state of the box ``[lb, ub]``
    (state order ``(p_y, ψ, v, δ)``; the ``p_y`` bounds are ignored, they may be infinite).
    Module docstring; ``|ψ|, |δ| < 90°`` on the box."""
    ts, wheelbase = _positive(ts, wheelbase, "jacobian_ldi")
    # p_y bounds may be infinite (ignored); ψ, v, δ are checked below
    lb = as_vector(lb, "jacobian_ldi: lb", 4, finite=False)
    ub = as_vector(ub, "jacobian_ldi: ub", 4, finite=False)
    for k, label in ((1, "psi"), (3, "delta")):
        if not (-np.pi / 2 < lb[k] <= ub[k] < np.pi / 2):
            raise BalustradeError(f"jacobian_ldi: the {label} range [{lb[k]}, {ub[k]}] must lie "
                             "inside (-90°, 90°)")
    if not (np.isfinite(lb[2]) and np.isfinite(ub[2]) and lb[2] <= ub[2]):
        raise BalustradeError(f"jacobian_ldi: the v range [{lb[2]}, {ub[2]}] must be finite")
    cos_psi = tuple(-c for c in reversed(_even_range(lambda t: -np.cos(t), lb[1], ub[1])))
    sec2 = _even_range(lambda t: 1.0 / np.cos(t) ** 2, lb[3], ub[3])
    v = (lb[2], ub[2])
    a1 = _interval_product(v, cos_psi)
    a4 = _interval_product(v, sec2)
    intervals = np.array([[ts * a1[0], ts * a1[1]],
                          [ts * np.sin(lb[1]), ts * np.sin(ub[1])],
                          [ts / wheelbase * np.tan(lb[3]), ts / wheelbase * np.tan(ub[3])],
                          [ts / wheelbase * a4[0], ts / wheelbase * a4[1]]])
    E = []
    for i, j in ((0, 1), (0, 2), (1, 2), (1, 3)):
        M = np.zeros((4, 4))
        M[i, j] = 1.0
        E.append(M)
    return np.eye(4), E, intervals


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
        # a state of the wrong length is a BalustradeError (numpy broadcast a (1,) state
        # against x_s silently); NaN entries give NaN, as the closed loops expect
        d = as_vector(x, "ShiftedCBF: x", self.x_s.size, finite=False) - self.x_s
        return float(d @ self.P @ d - 1.0)

    @property
    def policy(self) -> AffinePolicy:
        """``π_f(x) = K (x − x_s)`` as an explicit affine law (numbers and CasADi symbols;
        :mod:`balustrade.dsl.policies`), so controllers built with it emit C."""
        return AffinePolicy(self.K, x_s=self.x_s)

#: names that moved out of this module (issue #13): deprecated aliases (errors.moved_names)
__getattr__ = moved_names(__name__, {
    "bicycle_design": "balustrade.examples.bicycle",
})
