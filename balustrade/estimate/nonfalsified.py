"""The non-falsified parameter set Δ_k of (4.7) (SPEC §2.19).

For the model (4.6) ``x⁺ = A₀x + B₀u + D(x, u)θ + Ew`` and ``W = {H_w w <= h_w}``, one
transition ``(x_{k−1}, u_{k−1}) → x_k`` leaves the parameters that explain it with some
``w ∈ W``::

    Δ_k = {θ : −H_w E⁻¹ D(x_{k−1}, u_{k−1}) θ <= h_w − H_w E⁻¹ (x_k − A₀x_{k−1} − B₀u_{k−1})}

(``E = I`` in (4.7); an invertible ``E`` is folded into ``H_w``). Δ_k is a polyhedron, often
unbounded (``D`` has rank at most ``min(n, q)``), so it is returned as half-spaces, not as a
:class:`~balustrade.dsl.sets.Polytope` (which must be non-empty).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from balustrade._checks import as_vector
from balustrade.dsl.sets import Polytope
from balustrade.dsl.system_parametric import ParametricLinearSystem
from balustrade.errors import BalustradeError, ShapeError

#: a row of Δ_k whose θ-coefficients are below this (relative to the data) carries no
#: information on θ: it is dropped if satisfied, kept (and makes Δ_k empty) if violated
_ZERO_ROW = 1e-13
#: relative size of the rounding of ``h_w − H_w E⁻¹ r₀`` on rows without θ
_ROUNDING = 1e-12
#: a row of Δ_k is relaxed by this times the magnitude of the terms its ``h`` and ``Hθ`` are
#: computed from (16 machine epsilons: a bound on their floating-point rounding)
_ROW_ROUNDING = 16 * float(np.finfo(float).eps)


@dataclass(frozen=True)
class HalfSpaces:
    """``{θ : H θ <= h}``, possibly empty or unbounded; ``H`` may have zero rows (all θ)."""

    H: np.ndarray
    h: np.ndarray

    @property
    def dim(self) -> int:
        return int(self.H.shape[1])

    def contains(self, theta: np.ndarray, tol: float = 1e-9) -> bool:
        return bool(np.all(self.H @ theta - self.h <= tol))

    def intersect(self, other: Polytope | HalfSpaces) -> HalfSpaces:
        """Rows stacked: ``other``'s first."""
        return HalfSpaces(np.vstack([other.H, self.H]), np.concatenate([other.h, self.h]))


def disturbance_rows(system: ParametricLinearSystem, W: Polytope) -> np.ndarray:
    """``H_w E⁻¹``: the rows that test ``x⁺ − A₀x − B₀u − Dθ ∈ E W``; needs an invertible
    (square) ``E`` so that the residual determines ``w``."""
    if not isinstance(W, Polytope):
        raise BalustradeError(f"{system.name}: W must be a Polytope or Box (the disturbance "
                              f"set of (4.7)), got {type(W).__name__}")
    if W.dim != system.nw:
        raise ShapeError(f"{system.name}: W", f"dimension {system.nw} (nw)",
                         f"dimension {W.dim}", what="")
    E = system.E
    if E.shape[0] != E.shape[1] or np.linalg.matrix_rank(E) < E.shape[0]:
        raise BalustradeError(f"{system.name}: the set-membership update (4.7) needs an "
                              f"invertible E (w determined by the residual), got E of shape "
                              f"{E.shape} and rank {np.linalg.matrix_rank(E)}")
    return np.linalg.solve(E.T, W.H.T).T


def model_stack(system: ParametricLinearSystem) -> np.ndarray:
    """``[A_j, B_j]`` for ``j = 0 … q`` stacked as rows, shape ``((q + 1) n, n + m)``: one
    product with ``(x, u)`` gives the affine part ``A₀x + B₀u`` and the regressor
    ``D(x, u) = [A₁x + B₁u, …]`` of (4.7) at once (:func:`delta_rows`)."""
    return np.vstack([np.hstack([A, B]) for A, B in
                      zip((system.A0, *system.A_list), (system.B0, *system.B_list),
                          strict=True)])


def nonfalsified_set(system: ParametricLinearSystem, W: Polytope, x_prev: object,
                     u_prev: object, x_next: object,
                     Hw: np.ndarray | None = None) -> HalfSpaces:
    """Δ_k of (4.7) from one transition; ``Hw`` = :func:`disturbance_rows` if precomputed."""
    Hw = disturbance_rows(system, W) if Hw is None else Hw
    x_prev = as_vector(x_prev, f"{system.name}: x_prev", system.nx)
    u_prev = as_vector(u_prev, f"{system.name}: u_prev", system.nu)
    x_next = as_vector(x_next, f"{system.name}: x_next", system.nx)
    return delta_rows(model_stack(system), Hw, W.h, x_prev, u_prev, x_next)


def delta_rows(stack: np.ndarray, Hw: np.ndarray, hw: np.ndarray, x_prev: np.ndarray,
               u_prev: np.ndarray, x_next: np.ndarray) -> HalfSpaces:
    """Δ_k of (4.7) on checked vectors, with :func:`model_stack`'s ``stack``,
    ``Hw`` = :func:`disturbance_rows` and ``hw`` the bounds of ``W``: the per-step path of
    the estimators (one product for ``A₀x + B₀u`` and ``D(x, u)``, no repeated checks)."""
    n = x_prev.shape[0]
    parts = (stack @ np.concatenate([x_prev, u_prev])).reshape(-1, n)   # (q + 1, n)
    D = parts[1:].T
    r0 = x_next - parts[0]
    H = -Hw @ D
    Hw_r0 = Hw @ r0
    h = hw - Hw_r0
    scale = max(1.0, float(np.abs(Hw).max()) * max(1.0, float(np.abs(D).max())))
    informative = np.abs(H).max(axis=1) > _ZERO_ROW * scale
    # an uninformative row only matters if the data violate W there beyond rounding (a
    # vertex disturbance leaves h = ±1e-19 on the rows θ does not enter)
    rounding = _ROUNDING * max(1.0, float(np.abs(hw).max()), float(np.abs(Hw_r0).max()))
    keep = informative | (h < -rounding)
    # every informative row is relaxed by a bound on its own floating-point rounding before
    # the rows are scaled: a row whose θ-coefficients are tiny (~1e-12) would otherwise turn
    # the ~1e-19 rounding of its h into ~1e-7 after scaling, enough to put θ* outside Δ_k —
    # the 3-mass seeded runs then "falsified" the true model (session 10). Relaxing only
    # enlarges Δ_k (sound); on rows with ordinary coefficients it is ~1e-15 in θ.
    absHw = np.abs(Hw)
    terms = np.abs(hw) + absHw @ (np.abs(x_next) + np.abs(parts[0])) \
        + absHw @ np.abs(D).sum(axis=1)
    h = np.where(informative, h + _ROW_ROUNDING * terms, h)
    H, h = H[keep], h[keep]
    # rows scaled to unit ∞-norm (the same half-spaces): the LPs over the intersection of many
    # steps' rows (bounding boxes, support functions) are then equally conditioned per row
    norms = np.abs(H).max(axis=1) if H.shape[0] else np.zeros(0)
    norms = np.where(norms > 0, norms, 1.0)
    return HalfSpaces(H / norms[:, None], h / norms)


__all__ = ["HalfSpaces", "delta_rows", "disturbance_rows", "model_stack", "nonfalsified_set"]
