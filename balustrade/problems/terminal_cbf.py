"""Ellipsoidal terminal CBF synthesis, SDP (6.17) / (7.11) (SPEC §2.27).

``min −log det E`` s.t. ``[[λE, (AE+BY)ᵀ], [AE+BY, E]] ⪰ 0`` (invariance with strict
decrease, λ < 1 [Default]; λ = 1 is the printed LMI), ``[[(b̄_x,i − Δ)², a_iᵀE], [E a_i, E]] ⪰ 0``
for every state row and ``[[b̄_u,j², a_jᵀY], [Yᵀa_j, E]] ⪰ 0`` for every input row. Outputs
``P = E⁻¹``, ``K = Y P``, ``h_f(x) = xᵀPx − 1``, ``π_f(x) = Kx`` and
``γ_f = min_j b̄_u,j² / (a_jᵀ K E Kᵀ a_j) − 1``, the largest level with ``Kx ∈ U`` on
``D_f = {h_f <= γ_f}`` (SPEC §2.27 [Default]).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import casadi as ca
import cvxpy as cp
import numpy as np

from balustrade._checks import as_matrix, as_scalar, check_instance, check_psd
from balustrade.dsl.sets import Polytope
from balustrade.errors import BalustradeError, ShapeError


@dataclass(frozen=True)
class TerminalCBF:
    """``h_f(x) = xᵀPx − 1`` with ``π_f(x) = Kx`` valid on ``D_f = {h_f <= γ_f}``."""

    P: np.ndarray
    K: np.ndarray
    gamma_f: float
    decrease_factor: float = 1.0
    status: str = "optimal"
    solve_time: float = 0.0

    def __call__(self, x: object) -> object:
        """``h_f(x)`` on CasADi symbols or numbers."""
        if isinstance(x, (ca.SX, ca.MX, ca.DM)):
            return ca.mtimes([x.T, ca.DM(self.P), x]) - 1
        x = np.asarray(x, dtype=float).reshape(-1)
        return float(x @ self.P @ x - 1.0)

    def policy(self, x: np.ndarray) -> np.ndarray:
        """``π_f(x) = Kx``."""
        return self.K @ np.asarray(x, dtype=float).reshape(-1)

    @property
    def E(self) -> np.ndarray:
        return np.linalg.inv(self.P)


def synthesize_terminal_cbf(A: np.ndarray, B: np.ndarray, X: Polytope, U: Polytope,
                            delta_N: float = 0.0, decrease_factor: float = 0.99,
                            solver: str = "CLARABEL") -> TerminalCBF:
    """Solve (7.11)/(6.17) for ``x⁺ = Ax + Bu`` with state rows tightened by ``delta_N``
    (``Δ_{N−1}``) and return the terminal CBF. ``X``/``U`` may already be tightened by an
    RPI set (Chapters 5, 6). ``decrease_factor`` is ``λ`` in the invariance LMI."""
    A = as_matrix(A, "terminal CBF SDP: A")
    n = A.shape[0]
    if A.shape != (n, n):
        raise ShapeError("terminal CBF SDP: A", (n, n), A.shape)
    B = as_matrix(B, "terminal CBF SDP: B", (n, None))
    m = B.shape[1]
    check_instance(X, Polytope, "terminal CBF SDP: X")
    check_instance(U, Polytope, "terminal CBF SDP: U")
    delta_N = as_scalar(delta_N, "terminal CBF SDP: delta_N (Δ_{N−1})", low=0.0)
    decrease_factor = as_scalar(decrease_factor, "terminal CBF SDP: decrease factor λ")
    if not isinstance(solver, str):
        raise BalustradeError(f"terminal CBF SDP: solver must be a cvxpy solver name, got "
                              f"{type(solver).__name__}")
    if X.dim != n or U.dim != m:
        raise ShapeError("terminal CBF SDP: sets", f"X of dim {n}, U of dim {m}",
                         f"X of dim {X.dim}, U of dim {U.dim}", what="")
    if not 0 < decrease_factor <= 1:
        raise BalustradeError(f"terminal CBF SDP: decrease factor must lie in (0, 1], got "
                              f"{decrease_factor}")
    bx = X.h - delta_N
    if np.any(bx <= 0) or np.any(U.h <= 0):
        raise BalustradeError("terminal CBF SDP: the origin must lie in the interior of the "
                              f"(tightened) constraints; state bounds {bx}, input bounds {U.h}")
    E = cp.Variable((n, n), symmetric=True)
    Y = cp.Variable((m, n))
    AEBY = A @ E + B @ Y
    cons = [cp.bmat([[decrease_factor * E, AEBY.T], [AEBY, E]]) >> 0]
    for a, b in zip(X.H, bx):
        row = cp.reshape(a @ E, (1, n), order="F")
        cons.append(cp.bmat([[np.array([[b ** 2]]), row], [row.T, E]]) >> 0)
    for a, b in zip(U.H, U.h):
        row = cp.reshape(a @ Y, (1, n), order="F")
        cons.append(cp.bmat([[np.array([[b ** 2]]), row], [row.T, E]]) >> 0)
    prob = cp.Problem(cp.Minimize(-cp.log_det(E)), cons)
    start = time.perf_counter()
    try:
        prob.solve(solver=solver)
    except cp.error.SolverError as exc:
        raise BalustradeError(f"terminal CBF SDP: solver {solver} failed: {exc}") from exc
    elapsed = time.perf_counter() - start
    if prob.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE):
        raise BalustradeError(f"terminal CBF SDP: no solution ({prob.status}); the constraints "
                              "may admit no invariant ellipsoid")
    Ev = 0.5 * (E.value + E.value.T)
    P = np.linalg.inv(Ev)
    P = 0.5 * (P + P.T)
    K = Y.value @ P
    return TerminalCBF(P=P, K=K, gamma_f=largest_level(P, K, U), decrease_factor=decrease_factor,
                       status=prob.status, solve_time=elapsed)


def largest_level(P: np.ndarray, K: np.ndarray, U: Polytope) -> float:
    """``γ_f = min_j b_u,j² / (a_jᵀ K P⁻¹ Kᵀ a_j) − 1``: the largest ``γ`` with ``Kx ∈ U``
    on ``{xᵀPx − 1 <= γ}`` (SPEC §2.27 [Default])."""
    check_instance(U, Polytope, "largest_level: U")
    P = check_psd(P, "largest_level: P", strict=True)
    K = as_matrix(K, "largest_level: K", (U.dim, P.shape[0]))
    E = np.linalg.inv(P)
    levels = []
    for a, b in zip(U.H, U.h):
        s = float(a @ K @ E @ K.T @ a)
        levels.append(np.inf if s <= 0 else b ** 2 / s - 1.0)
    return float(min(levels))
