"""Causal linear controllers u_k = Σ_{j≤k} K_{k,j} x_j from the synthesis (3.15), in closed loop."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from balustrade._checks import as_matrix, as_vector
from balustrade.errors import ShapeError
from balustrade.problems.regret.operators import Operators


@dataclass(frozen=True)
class Rollout:
    """One closed-loop run: trajectories, cost J (3.3), non-causal optimum J* (3.6)."""

    x: np.ndarray        # (T+1, n)
    u: np.ndarray        # (T+1, m)
    w: np.ndarray        # (T, p)
    J: float
    J_star: float
    violation: float | None   # max(Hz − 1) over the run when constraints were given

    @property
    def regret(self) -> float:
        return self.J - self.J_star

    @property
    def ratio(self) -> float:
        """J / J* (competitive ratio of this run, (3.10))."""
        return self.J / self.J_star if self.J_star > 0 else float("inf")

    @property
    def satisfied(self) -> bool:
        return self.violation is None or self.violation <= 1e-7


class RegretController:
    """The causal state-feedback law of (3.15) with its responses Φ_u (for reference)."""

    def __init__(self, ops: Operators, K: np.ndarray, Phi_u: np.ndarray | None = None,
                 name: str = "controller"):
        size = (ops.m * (ops.T + 1), ops.n * (ops.T + 1))
        self.K = as_matrix(K, f"{name}: K", size)
        if not ops.is_causal(self.K, tol=0.0):
            raise ShapeError(f"{name}: K", "block lower-triangular (causal)", "non-causal entries",
                             what="structure")
        self.ops, self.Phi_u, self.name = ops, Phi_u, name

    def input(self, k: int, x_hist: np.ndarray) -> np.ndarray:
        """u_k = Σ_{j≤k} K_{k,j} x_j from the states x_0..x_k (rows of ``x_hist``)."""
        ops = self.ops
        rows = ops.u_blocks[k]
        cols = slice(0, ops.x_blocks[k].stop)
        return self.K[rows, cols] @ x_hist[: k + 1].reshape(-1)

    def simulate(self, x0: object, w: object, constraints=None) -> Rollout:
        """Closed loop x_{k+1} = A_k x_k + B_k u_k + E_k w_k for k < T, and u_T (cost only)."""
        ops, sysm = self.ops, self.ops.system
        T, n = ops.T, ops.n
        x0v = as_vector(x0, "x0", n)
        wm = np.asarray(w, dtype=float).reshape(T, -1) if np.size(w) == T * ops.p else None
        if wm is None:
            raise ShapeError("w", (T, ops.p), np.shape(w))
        x = np.zeros((T + 1, n))
        u = np.zeros((T + 1, ops.m))
        x[0] = x0v
        for k in range(T + 1):
            u[k] = self.input(k, x)
            if k < T:
                x[k + 1] = sysm.A[k] @ x[k] + sysm.B[k] @ u[k] + sysm.E[k] @ wm[k]
        J = ops.cost(x.reshape(-1), u.reshape(-1))
        J_star = ops.noncausal_cost(ops.delta(x0v, wm))
        viol = None if constraints is None else constraints.violation(x, u)
        return Rollout(x, u, wm, J, J_star, viol)
