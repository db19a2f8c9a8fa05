"""Stacked operators of the system level parametrization (thesis Section 3.2, SPEC 2.8–2.9).

For the linear time-varying system (3.1) ``x_{k+1} = A_k x_k + B_k u_k + E_k w_k`` over the task
horizon ``T`` this module builds

* the block down-shift ``Z`` and the block-diagonal ``𝒜``, ``ℬ``, ``ℰ`` of (3.5),
* the causal response maps ``F = (I − Z𝒜)⁻¹ Zℬ`` and ``G = (I − Z𝒜)⁻¹ ℰ`` (x = F u + G δ),
* the non-causal optimal input map (3.4) ``Φ_u^nc = −(ℛ + FᵀQF)⁻¹ FᵀQG``,
* the non-causal cost matrix ``𝒪`` of (3.6) with its partition (3.17),
* a square-root factor ``S`` (lower block-triangular, ``SᵀS = ℛ + Fᵀ𝒬F``) with which
  ``ΦᵀCΦ − 𝒪 = (S(Φ_u − Φ_u^nc))ᵀ (S(Φ_u − Φ_u^nc))`` for every achievable Φ: the regret is a
  sum of squares of ``m(T+1)`` rows instead of a difference of two quadratic forms, which is
  the compression every synthesis problem of :mod:`.synthesis` relies on.

Signals are stacked as in SPEC 2.8: ``x = (x_0..x_T)``, ``u = (u_0..u_T)``,
``δ = (x_0, w_0..w_{T−1})``.
δ-block ``0`` is ``x_0`` (size n), δ-block ``j ≥ 1`` is ``w_{j−1}`` (size p).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from balustrade._checks import as_matrix, check_psd
from balustrade.errors import BalustradeError, ShapeError


def _sequence(value: object, T: int, block: str, shape: tuple[int | None, int | None]
              ) -> list[np.ndarray]:
    """A matrix (time-invariant) or a length-T sequence of matrices, checked for shape."""
    if isinstance(value, (list, tuple)):
        if len(value) != T:
            raise ShapeError(block, f"a sequence of T={T} matrices", f"{len(value)} matrices",
                             what="length")
        mats = [as_matrix(v, f"{block}[{k}]", shape) for k, v in enumerate(value)]
        first = mats[0].shape
        for k, M in enumerate(mats):
            if M.shape != first:
                raise ShapeError(f"{block}[{k}]", first, M.shape)
        return mats
    M = as_matrix(value, block, shape)
    return [M] * T


@dataclass(frozen=True)
class LTVSystem:
    """A linear time-varying system (3.1) over the horizon ``T`` with quadratic cost (3.2).

    ``A``, ``B``, ``E``: one matrix (time-invariant) or ``T`` matrices; ``Q``, ``R``: one matrix
    or ``T + 1`` matrices (the cost (3.2) includes ``x_T`` and ``u_T``). ``E_k`` must be square
    and invertible (SPEC 2.8 [Gap]: full row rank plus a left-invertible ``ℰ`` force ``p = n``),
    so that ``Φ_x`` is invertible and (3.15) defines the controller.
    """

    A: list[np.ndarray]
    B: list[np.ndarray]
    E: list[np.ndarray]
    Q: list[np.ndarray]
    R: list[np.ndarray]
    T: int

    @classmethod
    def create(cls, A: object, B: object, T: int, E: object | None = None,
               Q: object | None = None, R: object | None = None) -> LTVSystem:
        """Validate and build; raises :class:`ShapeError`/:class:`NotPSDError` naming the input."""
        if not isinstance(T, (int, np.integer)) or T < 1:
            raise BalustradeError(f"T: the horizon must be a positive integer, got {T!r}")
        T = int(T)
        As = _sequence(A, T, "A", (None, None))
        n = As[0].shape[0]
        if As[0].shape != (n, n):
            raise ShapeError("A", (n, n), As[0].shape)
        Bs = _sequence(B, T, "B", (n, None))
        m = Bs[0].shape[1]
        Es = _sequence(np.eye(n) if E is None else E, T, "E", (n, None))
        for k, Ek in enumerate(Es):
            rank = np.linalg.matrix_rank(Ek)
            if rank < n:
                raise BalustradeError(
                    f"E[{k}]: must have full row rank n={n}, got rank {rank} (shape {Ek.shape})")
            if Ek.shape[1] != n:
                raise ShapeError(f"E[{k}]", (n, n), Ek.shape, what="shape (E_k must be square "
                                 "and invertible so that Φ_x is invertible, (3.15))")
        Qs = _sequence(np.eye(n) if Q is None else Q, T + 1, "Q", (n, n))
        Rs = _sequence(np.eye(m) if R is None else R, T + 1, "R", (m, m))
        Qs = [check_psd(Qk, f"Q[{k}]") for k, Qk in enumerate(Qs)]
        Rs = [check_psd(Rk, f"R[{k}]", strict=True) for k, Rk in enumerate(Rs)]
        return cls(As, Bs, Es, Qs, Rs, T)

    @property
    def n(self) -> int:
        return self.A[0].shape[0]

    @property
    def m(self) -> int:
        return self.B[0].shape[1]

    @property
    def p(self) -> int:
        return self.E[0].shape[1]


@dataclass(frozen=True)
class Operators:
    """All stacked quantities of SPEC 2.8 for one :class:`LTVSystem` (dense numpy arrays)."""

    system: LTVSystem
    Z: np.ndarray
    Acal: np.ndarray
    Bcal: np.ndarray
    Ecal: np.ndarray
    Qcal: np.ndarray
    Rcal: np.ndarray
    F: np.ndarray
    G: np.ndarray
    H: np.ndarray            # ℛ + Fᵀ𝒬F, the Hessian of J in u
    S: np.ndarray            # lower triangular, SᵀS = H
    Phi_u_nc: np.ndarray     # (3.4): ũ* = Φ_u^nc δ
    O: np.ndarray            # (3.6)
    u_blocks: list[slice] = field(repr=False)
    x_blocks: list[slice] = field(repr=False)
    d_blocks: list[slice] = field(repr=False)

    # --- sizes ----------------------------------------------------------------------------
    @property
    def T(self) -> int:
        return self.system.T

    @property
    def n(self) -> int:
        return self.system.n

    @property
    def m(self) -> int:
        return self.system.m

    @property
    def p(self) -> int:
        return self.system.p

    @property
    def nd(self) -> int:
        """Length of δ = (x_0, w): n + pT."""
        return self.n + self.p * self.T

    # --- partition (3.17) -----------------------------------------------------------------
    def partition(self, W: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(W_1, W_2, W_3) of a δ-space matrix partitioned as in (3.17)."""
        n = self.n
        return W[:n, :n], W[n:, :n], W[n:, n:]

    @property
    def O_parts(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self.partition(self.O)

    # --- maps ------------------------------------------------------------------------------
    def phi_x(self, Phi_u: np.ndarray) -> np.ndarray:
        """Φ_x = FΦ_u + G, the unique solution of the achievability constraint (3.14)."""
        return self.F @ Phi_u + self.G

    def achievability_residual(self, Phi_x: np.ndarray, Phi_u: np.ndarray) -> float:
        """max-abs residual of (3.14): [I − Z𝒜, −Zℬ] Φ − ℰ."""
        N = Phi_x.shape[0]
        res = (np.eye(N) - self.Z @ self.Acal) @ Phi_x - self.Z @ self.Bcal @ Phi_u - self.Ecal
        return float(np.max(np.abs(res)))

    def is_causal(self, M: np.ndarray, rows: str = "u", tol: float = 0.0) -> bool:
        """Whether a map from δ to u (or x) is causal: block (t, j) is zero for j > t."""
        blocks = self.u_blocks if rows == "u" else self.x_blocks
        for t, rs in enumerate(blocks):
            for j in range(t + 1, self.T + 1):
                if np.max(np.abs(M[rs, self.d_blocks[j]]), initial=0.0) > tol:
                    return False
        return True

    def regret_factor(self, Phi_u: np.ndarray) -> np.ndarray:
        """Y = S(Φ_u − Φ_u^nc), with ΦᵀCΦ − 𝒪 = YᵀY for the achievable Φ built from Φ_u."""
        return self.S @ (Phi_u - self.Phi_u_nc)

    def cost_matrix(self, Phi_x: np.ndarray, Phi_u: np.ndarray) -> np.ndarray:
        """ΦᵀCΦ: J(δ) = δᵀ(ΦᵀCΦ)δ for the closed loop (3.3)."""
        return Phi_x.T @ self.Qcal @ Phi_x + Phi_u.T @ self.Rcal @ Phi_u

    def cost(self, x: np.ndarray, u: np.ndarray) -> float:
        """J = xᵀ𝒬x + uᵀℛu (3.2)/(3.3) of stacked trajectories."""
        return float(x @ self.Qcal @ x + u @ self.Rcal @ u)

    def noncausal_cost(self, delta: np.ndarray) -> float:
        """J*(δ) = δᵀ𝒪δ (3.6)."""
        return float(delta @ self.O @ delta)

    def delta(self, x0: np.ndarray, w: np.ndarray) -> np.ndarray:
        """δ = (x_0, w_0, …, w_{T−1}); ``w`` is (T, p) or flat."""
        return np.concatenate([np.ravel(x0), np.ravel(w)])

    def causal_mask(self) -> np.ndarray:
        """Boolean mask of the free (causal) entries of Φ_u: block (t, j) with j ≤ t."""
        mask = np.zeros((self.m * (self.T + 1), self.nd), dtype=bool)
        for t, rs in enumerate(self.u_blocks):
            mask[rs, : self.d_blocks[t].stop] = True
        return mask

    def causal_selector(self, last_input: bool = True) -> sp.csc_matrix:
        """Sparse P with vec_F(Φ_u) = P θ, θ the causal entries of Φ_u in column-major order.

        ``last_input=False`` leaves out u_T: it affects no state of the horizon, so it enters
        J only through u_Tᵀ R_T u_T and J* not at all; u_T = 0 is optimal for every problem of
        Chapter 3 (and satisfies (3.40), whose right-hand sides are positive).
        """
        mask = self.causal_mask()
        if not last_input:
            mask[self.u_blocks[-1], :] = False
        idx = np.flatnonzero(mask.ravel(order="F"))
        return sp.csc_matrix((np.ones(idx.size), (idx, np.arange(idx.size))),
                             shape=(mask.size, idx.size))


def _blocks(sizes: Sequence[int]) -> list[slice]:
    out, start = [], 0
    for s in sizes:
        out.append(slice(start, start + s))
        start += s
    return out


def build_operators(system: LTVSystem) -> Operators:
    """Stack the system (SPEC 2.8) and precompute F, G, (3.4), (3.6) and the factor S."""
    n, m, p, T = system.n, system.m, system.p, system.T
    N, M = n * (T + 1), m * (T + 1)
    Z = np.kron(np.eye(T + 1, k=-1), np.eye(n))
    Acal = sla.block_diag(*system.A, np.zeros((n, n)))
    Bcal = sla.block_diag(*system.B, np.zeros((n, m)))
    Ecal = sla.block_diag(np.eye(n), *system.E)
    Qcal = sla.block_diag(*system.Q)
    Rcal = sla.block_diag(*system.R)
    # I − Z𝒜 is unit block lower-bidiagonal: solve instead of inverting.
    ImZA = np.eye(N) - Z @ Acal
    F = sla.solve_triangular(ImZA, Z @ Bcal, lower=True, unit_diagonal=True)
    G = sla.solve_triangular(ImZA, Ecal, lower=True, unit_diagonal=True)
    H = Rcal + F.T @ Qcal @ F
    H = 0.5 * (H + H.T)
    # Reverse-order Cholesky gives a LOWER triangular S with SᵀS = H, so that S keeps the
    # causal (block lower-triangular) pattern of Φ_u.
    flip = np.arange(M)[::-1]
    Lr = np.linalg.cholesky(H[np.ix_(flip, flip)])
    S = Lr.T[np.ix_(flip, flip)]
    FtQG = F.T @ Qcal @ G
    Phi_u_nc = -sla.cho_solve(sla.cho_factor(H), FtQG)
    O = G.T @ Qcal @ G + FtQG.T @ Phi_u_nc
    O = 0.5 * (O + O.T)
    return Operators(system, Z, Acal, Bcal, Ecal, Qcal, Rcal, F, G, H, S, Phi_u_nc, O,
                     _blocks([m] * (T + 1)), _blocks([n] * (T + 1)), _blocks([n] + [p] * T))


def noncausal_cost_matrix_alt(ops: Operators) -> np.ndarray:
    """The first form of (3.6): 𝒪 = Gᵀ𝒬(I + Fℛ⁻¹Fᵀ𝒬)⁻¹G (used to cross-check :attr:`O`)."""
    N = ops.F.shape[0]
    inner = np.eye(N) + ops.F @ np.linalg.solve(ops.Rcal, ops.F.T) @ ops.Qcal
    return ops.G.T @ ops.Qcal @ np.linalg.solve(inner, ops.G)


def responses_from_controller(ops: Operators, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Φ_x, Φ_u of a causal controller u = Kx, (3.12)."""
    N = ops.Z.shape[0]
    Phi_x = np.linalg.solve(np.eye(N) - ops.Z @ (ops.Acal + ops.Bcal @ K), ops.Ecal)
    return Phi_x, K @ Phi_x


def controller_from_responses(ops: Operators, Phi_x: np.ndarray, Phi_u: np.ndarray
                              ) -> np.ndarray:
    """K = Φ_u Φ_x⁻¹ (3.15); Φ_x is block lower triangular with diagonal blocks I, E_0, …."""
    K = np.linalg.solve(Phi_x.T, Phi_u.T).T
    # exact zeros above the block diagonal (causality), removing round-off
    for t, rs in enumerate(ops.u_blocks):
        K[rs, ops.x_blocks[t].stop:] = 0.0
    return K
