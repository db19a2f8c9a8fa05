"""The robust PCBF's candidate, terminal input and slack polishing (thesis Sections 5.5
and 6.4): the numerical steps Algorithms 5.2 and 6.4 take between solves.

* :func:`slack_cost` — ``h̃(ξ) = α_f ξ_N + Σ_i ‖ξ_i‖`` (SPEC §1.12), the value of (5.15);
* :func:`robust_candidate` — the shifted candidate (5.17) (with the SPEC §2.23 corrections:
  ``ξ*_{i+1|k}`` in the shift and ``c_x^E`` in the (N−1)-th slack), also the warm start (6.14);
* :func:`terminal_input` — ``π_f(z_N)``, or the input of ``U ⊖ κ(E)`` with the largest
  decrease of ``h_f`` where ``π_f`` leaves it;
* :func:`minimal_slacks`, :func:`polished_slacks` — the smallest slacks a nominal
  trajectory needs, removing an interior-point solver's slack residue.

The formulations (5.15), (5.16) themselves are in :mod:`balustrade.problems.robust`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.optimize

from balustrade._checks import as_matrix, as_scalar, check_norm_order
from balustrade.dsl.sets import Polytope
from balustrade.dsl.system import System
from balustrade.errors import BalustradeError
from balustrade.problems._args import positive


def slack_cost(xi: np.ndarray, xi_N: float, alpha_f: float, slack_norm: int | float = 1
               ) -> float:
    """``h̃(ξ) = α_f ξ_N + Σ_i ‖ξ_i‖`` (SPEC §1.12); ``xi`` has one column per step."""
    xi = as_matrix(xi, "slack_cost: xi")
    xi_N = as_scalar(xi_N, "slack_cost: xi_N")
    alpha_f = positive(alpha_f, "slack_cost: alpha_f")
    check_norm_order(slack_norm, "slack_cost: slack_norm")
    return float(alpha_f * xi_N + np.linalg.norm(xi, slack_norm, axis=0).sum())


@dataclass
class Candidate:
    """A candidate (warm start) ``(z̃, ṽ, ξ̃, ξ̃_N)`` for the next step ((5.17), (6.14))."""

    z: np.ndarray
    v: np.ndarray
    xi: np.ndarray
    xi_N: float

    def as_dict(self) -> dict[str, np.ndarray]:
        return {"z": self.z, "v": self.v, "xi": self.xi, "xi_N": np.array([[self.xi_N]])}


def robust_candidate(system: System, X_E: Polytope, h_f: Callable, pi_f: Callable,
                     deltas: np.ndarray, z: np.ndarray, v: np.ndarray, xi: np.ndarray,
                     U_E: Polytope | None = None) -> Candidate:
    """(5.17) / (6.14a–c) from a feasible ``(z, v, ξ)`` at time ``k``:

    * ``ṽ = (v_1, …, v_{N−1}, v_f)``, ``z̃ = (z_1, …, z_N, f(z_N, v_f, 0))`` with
      ``v_f = π_f(z_N)`` (6.14a), or, when ``U_E`` is given and ``π_f(z_N) ∉ U ⊖ κ(E)``
      (``z_N`` outside ``D_f``), the input of :func:`terminal_input` ("any input satisfying the
      ``h_f`` decrease within ``U ⊖ κ(E)``", (5.17));
    * ``ξ̃_i = max(0, ξ_{i+1} + (Δ_i − Δ_{i+1}) 1)`` for ``i ∈ I[0, N−2]`` (SPEC [Typo?]:
      ``ξ_{i+1|k}``), ``ξ̃_{N−1} = max(0, c_x^E(z_N) + Δ_{N−1} 1)`` (SPEC [Gap]: ``c_x^E``),
      ``ξ̃_N = max(0, h_f(z̃_N))``.
    """
    z = np.asarray(z, dtype=float)
    v = np.asarray(v, dtype=float).reshape(system.nu, -1)
    xi = np.asarray(xi, dtype=float).reshape(X_E.n_rows, -1)
    N = v.shape[1]
    deltas = np.asarray(deltas, dtype=float).reshape(-1)
    if deltas.size != N or z.shape != (system.nx, N + 1) or xi.shape != (X_E.n_rows, N):
        raise BalustradeError(f"robust_candidate: expected z of shape {(system.nx, N + 1)}, "
                              f"{N} tightenings and xi of shape {(X_E.n_rows, N)}, got "
                              f"{z.shape}, {deltas.size} and {xi.shape}")
    zN = z[:, N]
    u_f = terminal_input(system, h_f, pi_f, zN, U_E)
    z_next = np.asarray(system.step(zN, u_f, np.zeros(system.nw) if system.nw else None),
                        dtype=float).reshape(-1)
    z_t = np.column_stack([z[:, 1:], z_next])
    v_t = np.column_stack([v[:, 1:], u_f]) if N > 1 else u_f.reshape(-1, 1)
    xi_t = np.empty_like(xi)
    # column i: ξ_{i+1} + (Δ_i − Δ_{i+1}), the same operations as entry by entry
    np.maximum(0.0, xi[:, 1:] + (deltas[:-1] - deltas[1:]), out=xi_t[:, :N - 1])
    xi_t[:, N - 1] = np.maximum(0.0, X_E.H @ zN - X_E.h + deltas[N - 1])
    xi_N = max(0.0, float(h_f(z_next)))
    return Candidate(z_t, v_t, xi_t, xi_N)


#: tolerance of ``U_E.contains`` in :func:`terminal_input` (``tube_functions.CONTAINS_TOL``,
#: the same test in the CasADi candidate and its emitted C)
CONTAINS_TOL = 1e-12


def terminal_input(system: System, h_f: Callable, pi_f: Callable, z_N: np.ndarray,
                   U_E: Polytope | None = None) -> np.ndarray:
    """``v*_k(z_N)`` of (5.17): ``π_f(z_N)`` if it lies in ``U ⊖ κ(E)`` (always on ``D_f``,
    Assumption 6.14), otherwise ``argmin_{v ∈ U ⊖ κ(E)} h_f(f(z_N, v, 0))`` — the largest
    decrease of ``h_f`` any admissible input achieves (a small SLSQP problem)."""
    u_f = np.asarray(pi_f(z_N), dtype=float).reshape(-1)
    if U_E is None or U_E.contains(u_f, tol=CONTAINS_TOL):
        return u_f
    w0 = np.zeros(system.nw) if system.nw else None

    def value(v: np.ndarray) -> float:
        return float(h_f(np.asarray(system.step(z_N, v, w0), dtype=float).reshape(-1)))

    start = U_E.project(u_f)
    res = scipy.optimize.minimize(value, start, method="SLSQP",
                                  constraints=[{"type": "ineq",
                                                "fun": lambda v: U_E.h - U_E.H @ v,
                                                "jac": lambda v: -U_E.H}],
                                  options={"ftol": 1e-12, "maxiter": 200})
    v = np.asarray(res.x, dtype=float)
    if not U_E.contains(v, tol=CONTAINS_TOL):
        v = U_E.project(v)
    return v if value(v) <= value(start) else start


def minimal_slacks(X_E: Polytope, h_f: Callable, deltas: np.ndarray, z: np.ndarray
                   ) -> tuple[np.ndarray, float]:
    """The smallest slacks a nominal trajectory ``z`` needs in (5.15e–f):
    ``ξ_i = max(0, c_x^E(z_i) + Δ_i 1)``, ``ξ_N = max(0, h_f(z_N))`` (SPEC §1.4).

    Applied to an interior-point optimizer of (5.15)/(6.15) it removes the barrier's slack
    residue (an interior-point solver leaves ``α_f ξ_N ≈ 10⁻⁶…10⁻⁵`` on ``S_r``) without
    changing ``z``, so the polished ``h̃`` is an upper bound on ``h_r`` at least as tight as
    the solver's value."""
    z = np.asarray(z, dtype=float)
    deltas = np.asarray(deltas, dtype=float).reshape(-1)
    N = deltas.size
    xi = np.maximum(0.0, X_E.H @ z[:, :N] - X_E.h[:, None] + deltas[None, :])
    return xi, max(0.0, float(h_f(z[:, N])))


def polished_slacks(solution, X_E: Polytope, h_f: Callable, deltas: np.ndarray
                    ) -> tuple[np.ndarray, float]:
    """Elementwise minimum of a solution's slacks and :func:`minimal_slacks` of its ``z``."""
    xi = np.maximum(np.asarray(solution["xi"], dtype=float).reshape(X_E.n_rows, -1), 0.0)
    xi_N = max(float(np.asarray(solution["xi_N"]).reshape(-1)[0]), 0.0)
    xi_min, xi_N_min = minimal_slacks(X_E, h_f, deltas, solution["z"])
    return np.minimum(xi, xi_min), min(xi_N, xi_N_min)


__all__ = ["CONTAINS_TOL", "Candidate", "minimal_slacks", "polished_slacks", "robust_candidate",
           "slack_cost", "terminal_input"]
