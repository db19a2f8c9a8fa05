"""Decision variables of the system level synthesis and the affine maps built on them.

Only the causal (block lower-triangular) entries of Φ_u are variables (SPEC 2.9 [Default]);
Φ_x = FΦ_u + G satisfies the achievability constraint (3.14) by construction, and the regret
factor Y = S(Φ_u − Φ_u^nc) (:mod:`.operators`) is an explicit sparse affine map of them.
The constraint rows H_zΦ of (3.41) are built the same way.
"""

from __future__ import annotations

import cvxpy as cp
import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from balustrade._checks import as_matrix
from balustrade.errors import BalustradeError, ShapeError
from balustrade.problems.regret.operators import Operators


class Parametrization:
    """θ = causal entries of Φ_u, with sparse maps to Y(θ) and Φ(θ)."""

    def __init__(self, ops: Operators):
        self.ops = ops
        self.P = ops.causal_selector()
        self.theta = cp.Variable(self.P.shape[1], name="Phi_u_causal")
        M, nd = ops.m * (ops.T + 1), ops.nd
        self.M = M
        self.AY = (sp.kron(sp.identity(nd, format="csr"), sp.csr_matrix(ops.S)) @ self.P).tocsr()
        self.cY = -(ops.S @ ops.Phi_u_nc).ravel(order="F")

    # --- regret factor -----------------------------------------------------------------------
    def Y(self, cols: slice) -> cp.Expression:
        """Y[:, cols] (M × |cols|) as a cvxpy expression."""
        rows = slice(cols.start * self.M, cols.stop * self.M)
        k = cols.stop - cols.start
        return cp.reshape(self.AY[rows] @ self.theta + self.cY[rows], (self.M, k), order="F")

    def Y_times(self, cols: slice, U: np.ndarray) -> cp.Expression:
        """Y[:, cols] @ U (M × U.shape[1]) as an explicit sparse affine map of θ."""
        rows = slice(cols.start * self.M, cols.stop * self.M)
        kronU = sp.kron(sp.csr_matrix(U.T), sp.identity(self.M, format="csr"), format="csr")
        A = (kronU @ self.AY[rows]).tocsr()
        c = kronU @ self.cY[rows]
        return cp.reshape(A @ self.theta + c, (self.M, U.shape[1]), order="F")

    def Y_x0(self, x0: np.ndarray) -> cp.Expression:
        """Y[:, x₀-block] @ x₀, an M-vector (the C^{1/2}Φ⁰x₀ of (3.19) after compression)."""
        return self.Y_times(self.ops.d_blocks[0], x0.reshape(-1, 1))[:, 0]

    # --- values --------------------------------------------------------------------------------
    def phi_u_value(self) -> np.ndarray:
        ops = self.ops
        return (self.P @ self.theta.value).reshape((self.M, ops.nd), order="F")

    # --- constraint rows (3.40)/(3.41) --------------------------------------------------------
    def constraint_rows(self, Hx: np.ndarray, Hu: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(H_Φ, H_c, times) with H_zΦ = H_Φ Φ_u + H_c, and the time step of each row."""
        ops = self.ops
        T = ops.T
        HxB = sla.block_diag(*([Hx] * (T + 1)))
        HuB = sla.block_diag(*([Hu] * (T + 1)))
        H_phi = np.vstack([HxB @ ops.F, HuB])
        H_c = np.vstack([HxB @ ops.G, np.zeros((HuB.shape[0], ops.nd))])
        times = np.concatenate([np.repeat(np.arange(T + 1), Hx.shape[0]),
                                np.repeat(np.arange(T + 1), Hu.shape[0])])
        return H_phi, H_c, times

    def robust_constraints(self, Hx: np.ndarray, Hu: np.ndarray, x0: np.ndarray | None,
                           P_half_inv: np.ndarray) -> list[cp.Constraint]:
        """SOC form of (3.41): [H_z]_iΦ⁰x₀ + Σ_j ‖[H_z]_i[[Φ^w]]_j P^{-1/2}‖ ≤ 1 for every row i.

        Rows and blocks that are structurally zero (w_{j−1} cannot affect time t < j) are
        skipped. With ``x0 = None`` the initial-state column is required to vanish from the
        constraint (the constraint must then hold for the nominal x₀ = 0).
        """
        ops = self.ops
        H_phi, H_c, times = self.constraint_rows(Hx, Hu)
        nr, p = H_phi.shape[0], ops.p
        M = self.M
        PmhT = sp.csr_matrix(np.where(np.abs(P_half_inv) > 0, P_half_inv, 0.0).T)
        pieces, consts, pair_rows = [], [], []
        for j in range(1, ops.T + 1):
            cols = ops.d_blocks[j]
            rows = np.flatnonzero(times >= j)
            if rows.size == 0:
                continue
            Pj = self.P[cols.start * M: cols.stop * M]
            A = sp.kron(PmhT, sp.csr_matrix(H_phi[rows]), format="csr") @ Pj
            c = (H_c[rows][:, cols] @ P_half_inv).ravel(order="F")
            pieces.append((A.tocsr(), c, rows.size))
            pair_rows.append(rows)
        exprs = [cp.reshape(A @ self.theta + c, (k, p), order="F") for A, c, k in pieces]
        X = cp.vstack(exprs)
        npairs = X.shape[0]
        s = cp.Variable(npairs, nonneg=True)
        all_rows = np.concatenate(pair_rows)
        summ = sp.csr_matrix((np.ones(npairs), (all_rows, np.arange(npairs))), shape=(nr, npairs))
        cons: list[cp.Constraint] = [cp.SOC(s, X, axis=1)]
        lhs = summ @ s
        if x0 is not None:
            cols0 = ops.d_blocks[0]
            P0 = self.P[cols0.start * M: cols0.stop * M]
            A0 = sp.kron(sp.csr_matrix(x0.reshape(1, -1)), sp.csr_matrix(H_phi), format="csr")
            lhs = lhs + (A0 @ P0) @ self.theta + H_c[:, cols0] @ x0
        consts.append(lhs <= 1)
        return cons + consts


def normalize_halfspaces(A: object, b: object, block: str) -> np.ndarray:
    """Rows a_iᵀz ≤ b_i with b_i > 0 rewritten as (a_i/b_i)ᵀz ≤ 1, the form (3.40)."""
    A = as_matrix(A, f"{block} (A)")
    b = np.asarray(b, dtype=float).reshape(-1)
    if b.size != A.shape[0]:
        raise ShapeError(f"{block} (b)", (A.shape[0],), b.shape)
    if np.any(b <= 0):
        raise BalustradeError(f"{block}: the form (3.40) needs the origin in the interior "
                              f"(all b_i > 0), got b = {b}")
    return A / b[:, None]
