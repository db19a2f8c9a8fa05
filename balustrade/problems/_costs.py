"""The quadratic stage and trajectory costs shared by the formulations.

``l(x, u) = xᵀQx + uᵀRu`` and ``Σ_{i<M} l(x_i, u_i) + x_MᵀPx_M`` — the cost of (2.9),
(2.11), (2.14), (2.15) and, scaled by ½, of the Lyapunov design (6.2)/(6.10). One helper
for CasADi columns (inside a formulation) and numpy vectors (evaluating ``V`` of (6.2)),
so the expression a builder minimizes and the value an algorithm computes are the same
formula. Weights are checked by the builders (``_args.check_weights``) before they get here.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

Symbolic = ca.SX | ca.MX | ca.DM


def _quad(a: object, W: np.ndarray) -> object:
    if isinstance(a, Symbolic):
        return ca.mtimes([a.T, ca.DM(W), a])
    a = np.asarray(a, dtype=float).reshape(-1)
    return float(a @ W @ a)


def stage_cost(x: object, u: object, Q: np.ndarray, R: np.ndarray) -> object:
    """``l(x, u) = xᵀQx + uᵀRu`` for CasADi columns (an expression) or vectors (a float)."""
    return _quad(x, Q) + _quad(u, R)


def trajectory_cost(x: object, u: object, Q: np.ndarray, R: np.ndarray, P: np.ndarray
                    ) -> object:
    """``Σ_{i<M} l(x_i, u_i) + x_MᵀPx_M`` for states ``x`` with ``M + 1`` columns and inputs
    ``u`` with ``M`` columns (CasADi matrices or numpy arrays of shape ``(n, M+1)``,
    ``(m, M)``)."""
    M = u.shape[1]
    total = ca.SX(0) if isinstance(x, Symbolic) else 0.0
    for i in range(M):
        total = total + stage_cost(x[:, i], u[:, i], Q, R)
    return total + _quad(x[:, M], P)


__all__ = ["stage_cost", "trajectory_cost"]
