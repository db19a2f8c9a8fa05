"""The unstable 2-D system of thesis Section 5.6 (SPEC §3.3).

``x⁺ = [[1, 0.1], [0.11, 1]] x + [0, 0.1]ᵀ u + w`` (the printed equation lacks ``u``; SPEC
[Typo?]), ``|x₁| <= 1``, ``|x₂| <= 10``, ``|u| <= 2.5``, ``‖w‖∞ <= 0.03``; PCBF settings
``N = 100``, ``Δ_i = i·10⁻⁴``, ``α_f = 10⁶``, ``x₀ = (0, 1)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from balustrade.dsl.sets import Box
from balustrade.dsl.system import LinearSystem
from balustrade.models.setups import RobustPCBFSetup

A = np.array([[1.0, 0.1], [0.11, 1.0]])
B = np.array([[0.0], [0.1]])
W_BOUND = 0.03


def unstable2d() -> LinearSystem:
    """``x⁺ = A x + B u + w`` with ``w ∈ R²`` entering additively (``E = I``)."""
    return LinearSystem(A, B, np.eye(2), name="unstable2d")


@dataclass(frozen=True)
class Unstable2DSetup(RobustPCBFSetup):
    """Sets and PCBF settings of Section 5.6 (``Δ_i = i · 10⁻⁴``, N = 100)."""

    x0: tuple[float, float] = (0.0, 1.0)


def unstable2d_setup(N: int = 100) -> Unstable2DSetup:
    return Unstable2DSetup(X=Box.symmetric([1.0, 10.0], name="X"),
                           U=Box.symmetric([2.5], name="U"),
                           W=Box.symmetric([W_BOUND, W_BOUND], name="W"), N=N)
