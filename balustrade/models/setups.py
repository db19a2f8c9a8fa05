"""Common shape of the settings of the linear robust-PCBF examples (Chapters 5 and 6)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from balustrade.dsl.sets import Box


@dataclass(frozen=True)
class RobustPCBFSetup:
    """Constraint sets X, U, disturbance set W, horizon N and the PCBF constants of (2.24):
    the tightening sequence ``Δ_i = i · delta_step`` and the terminal slack weight α_f."""

    X: Box
    U: Box
    W: Box
    N: int = 100
    delta_step: float = 1e-4
    alpha_f: float = 1e6

    def deltas(self, N: int | None = None) -> np.ndarray:
        """``Δ_i = i · delta_step`` for ``i ∈ I[0, N−1]`` (default: this setup's N)."""
        return self.delta_step * np.arange(self.N if N is None else N)
