"""Decision variables of the system level synthesis and the affine maps built on them.

The variables are the causal (block lower-triangular) entries of Ψ = SΦ_u (SPEC 2.9
[Default]), S the lower block-triangular square-root factor of :mod:`.operators`: Ψ is causal
exactly when Φ_u is, and the regret factor Y = S(Φ_u − Φ_u^nc) = Ψ − SΦ_u^nc is then an entry
selection plus a constant (each variable enters one entry of Y instead of a column of S, which
keeps the LMIs sparse). Φ_u = S⁻¹Ψ, and Φ_x = FΦ_u + G satisfies the achievability constraint
(3.14) by construction. The constraint rows H_zΦ of (3.41) are affine maps of the same θ.
The last input u_T is fixed to zero (it cannot affect the states of the horizon, see
:meth:`.Operators.causal_selector`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from balustrade._checks import as_matrix
from balustrade.dsl.synthesis_arrow import AffineMap
from balustrade.errors import BalustradeError, ShapeError
from balustrade.problems.regret.operators import Operators


@dataclass(frozen=True)
class RobustRows:
    """(3.41) as data: G s + fixed + Fθ + g ≤ 1 with s_k ≥ ‖row k of the stacked pieces‖."""

    pieces: tuple[AffineMap, ...]     # (rows_k, p) each; their rows, stacked, are the norms s
    G: sp.csr_matrix                  # inequality rows × Σ rows_k
    fixed: np.ndarray                 # norm terms that do not depend on θ
    F: sp.csr_matrix | None = None    # the x₀ column, when x₀ is given
    g: np.ndarray | None = None


class Parametrization:
    """θ = causal entries of Ψ = SΦ_u, with sparse maps to Y(θ) and Φ(θ) (data, no solver)."""

    def __init__(self, ops: Operators):
        self.ops = ops
        self.P = ops.causal_selector(last_input=False)
        self.n_theta = self.P.shape[1]
        self.M = ops.m * (ops.T + 1)
        self.S_inv = sla.solve_triangular(ops.S, np.eye(self.M), lower=True)
        self.AY = self.P.tocsr()
        self.cY = -(ops.S @ ops.Phi_u_nc).ravel(order="F")
        self._Y = AffineMap(self.AY, self.cY, (self.M, ops.nd))

    # --- regret factor -----------------------------------------------------------------------
    def Y(self, cols: slice) -> AffineMap:
        """Y[:, cols] (M × |cols|) as an affine map of θ."""
        return self._Y.columns(cols)

    def Y_map(self, cols: slice, U: np.ndarray | None = None) -> tuple[sp.csr_matrix, np.ndarray]:
        """(A, c) with vec_F(Y[:, cols] U) = Aθ + c (U = I when omitted)."""
        m = self.Y(cols) if U is None else self.Y(cols).times(U)
        return m.A, m.c

    def Y_x0(self, x0: np.ndarray) -> AffineMap:
        """Y[:, x₀-block] @ x₀, an M-vector (the C^{1/2}Φ⁰x₀ of (3.19) after compression)."""
        return self.Y(self.ops.d_blocks[0]).times(x0.reshape(-1, 1))

    # --- values --------------------------------------------------------------------------------
    def phi_u_value(self, theta: np.ndarray) -> np.ndarray:
        ops = self.ops
        Psi = (self.P @ theta).reshape((self.M, ops.nd), order="F")
        return self.S_inv @ Psi

    # --- constraint rows (3.40)/(3.41) --------------------------------------------------------
    def constraint_rows(self, Hx: np.ndarray, Hu: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(H_Ψ, H_c, times) with H_zΦ = H_Ψ Ψ + H_c, and the time step of each row."""
        ops = self.ops
        T = ops.T
        HxB = sla.block_diag(*([Hx] * (T + 1)))
        HuB = sla.block_diag(*([Hu] * (T + 1)))
        H_phi = np.vstack([HxB @ ops.F, HuB]) @ self.S_inv
        H_c = np.vstack([HxB @ ops.G, np.zeros((HuB.shape[0], ops.nd))])
        times = np.concatenate([np.repeat(np.arange(T + 1), Hx.shape[0]),
                                np.repeat(np.arange(T + 1), Hu.shape[0])])
        return H_phi, H_c, times

    def robust_constraints(self, Hx: np.ndarray, Hu: np.ndarray, x0: np.ndarray | None,
                           P_half_inv: np.ndarray) -> RobustRows:
        """SOC form of (3.41): [H_z]_iΦ⁰x₀ + Σ_j ‖[H_z]_i[[Φ^w]]_j P^{-1/2}‖ ≤ 1 for every row i.

        Rows and blocks that are structurally zero (w_{j−1} cannot affect time t < j) are
        skipped. Parallel rows of one step (h and −h of a box, or rows αh) have proportional
        norm terms, ‖(αh)ᵀΦP^{-1/2}‖ = |α|·‖hᵀΦP^{-1/2}‖, so they share one set of SOC epigraph
        variables (exact; halves the cones for symmetric bounds). With ``x0 = None`` the
        initial-state column is required to vanish from the constraint (the constraint must
        then hold for the nominal x₀ = 0).
        """
        ops = self.ops
        H_phi, H_c, times = self.constraint_rows(Hx, Hu)
        rep_of, scale = parallel_rows(np.hstack([H_phi, H_c]), times)
        reps = np.unique(rep_of)
        nr, p = H_phi.shape[0], ops.p
        M = self.M
        PmhT = sp.csr_matrix(np.where(np.abs(P_half_inv) > 0, P_half_inv, 0.0).T)
        pieces, pair_rows = [], []
        fixed = np.zeros(nr)        # Σ_j of the norm terms that do not depend on θ, per rep
        for j in range(1, ops.T + 1):
            cols = ops.d_blocks[j]
            rows = reps[times[reps] >= j]
            k = rows.size
            if k == 0:
                continue
            Pj = self.P[cols.start * M: cols.stop * M]
            A = (sp.kron(PmhT, sp.csr_matrix(H_phi[rows]), format="csr") @ Pj).tocsr()
            c = (H_c[rows][:, cols] @ P_half_inv).ravel(order="F")
            # entry (pair i, coordinate q) is row i + k·q; pairs without θ (x_t's response to
            # w_{t−1} is the constant E) are a number, not a cone
            free = (A.getnnz(axis=1).reshape(p, k) > 0).any(axis=0)
            fixed[rows[~free]] += np.linalg.norm(c.reshape(p, k)[:, ~free], axis=0)
            if free.any():
                keep = (np.flatnonzero(free)[None, :] + k * np.arange(p)[:, None]).ravel()
                pieces.append(AffineMap(A[keep].tocsr(), c[keep], (int(free.sum()), p)))
                pair_rows.append(rows[free])
        # row i of (3.41) is |α_i| times the terms of its representative rep_i
        expand = sp.csr_matrix((np.abs(scale), (np.arange(nr), rep_of)), shape=(nr, nr))
        if pieces:
            pair_rep = np.concatenate(pair_rows)
            npairs = pair_rep.size
            to_rep = sp.csr_matrix((np.ones(npairs), (pair_rep, np.arange(npairs))),
                                   shape=(nr, npairs))
            G = (expand @ to_rep).tocsr()
        else:
            G = sp.csr_matrix((nr, 0))
        F = g = None
        if x0 is not None:
            cols0 = ops.d_blocks[0]
            P0 = self.P[cols0.start * M: cols0.stop * M]
            A0 = sp.kron(sp.csr_matrix(x0.reshape(1, -1)), sp.csr_matrix(H_phi), format="csr")
            F, g = (A0 @ P0).tocsr(), H_c[:, cols0] @ x0
        return RobustRows(tuple(pieces), G, expand @ fixed, F, g)


def parallel_rows(R: np.ndarray, groups: np.ndarray, rtol: float = 1e-12
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(rep, α): row i of R equals α_i · row rep_i, rep_i the first row of the same group
    parallel to it (rep_i = i and α_i = 1 for representatives). Zero rows are never
    representatives of others (a zero row gets α = 0 if its group has a nonzero row)."""
    n = R.shape[0]
    rep, alpha = np.arange(n), np.ones(n)
    for g in np.unique(groups):
        members = np.flatnonzero(groups == g)
        for pos, i in enumerate(members):
            for r in members[:pos]:
                if rep[r] != r or not np.any(R[r]):
                    continue
                a = float(R[i] @ R[r]) / float(R[r] @ R[r])
                if np.linalg.norm(R[i] - a * R[r]) <= rtol * np.linalg.norm(R[i]):
                    rep[i], alpha[i] = r, a
                    break
    return rep, alpha


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
