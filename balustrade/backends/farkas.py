"""An independent check of a primal infeasibility certificate (Farkas' lemma for the conic
form of :mod:`~balustrade.backends.passes.to_conic`).

The constraints ``A y + s = b, s ∈ K`` (``K`` = zero cone × ℝ₊ × second-order cones) have
no solution if some ``z ∈ K*`` has ``Aᵀz = 0`` and ``bᵀz < 0``: for a feasible ``y`` the
slack ``s = b − A y ∈ K`` gives ``0 <= zᵀs = bᵀz − (Aᵀz)ᵀy``. A solver's certificate holds
only up to its tolerances, so the check makes the argument quantitative instead of trusting
the solver's word:

1. ``z`` is projected onto ``K*`` (zero rows: free; nonnegative rows: clipped at 0; cones:
   the Euclidean projection onto the self-dual second-order cone), so ``zᵀs >= 0`` holds
   exactly for every ``s ∈ K``;
2. with ``r = Aᵀz`` the inequality ``rᵀy <= bᵀz < 0`` must hold for every feasible ``y``, so
   no feasible ``y`` has ``‖y‖∞ < R = −bᵀz / ‖r‖₁`` — the *radius* the certificate rules
   out (``R = ∞`` for an exact certificate);
3. the certificate is accepted if ``R >= RADIUS_FACTOR · max(1, ‖b‖∞)``: a verdict
   "infeasible" then means that no point of that size satisfies the constraints.

A bogus certificate (e.g. a multiplier vector of a feasible problem, ``Aᵀz = −(P y + q)``)
rules out a radius of the order of the solution itself and is rejected.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

#: a certificate must rule out every point with ``‖y‖∞ < RADIUS_FACTOR · max(1, ‖b‖∞)``
RADIUS_FACTOR = 1e6


@dataclass
class FarkasCheck:
    """The outcome of :func:`check_farkas`: ``valid``, the radius ``R`` ruled out, the bound
    it had to reach, and the words for a status message."""

    valid: bool
    radius: float
    required: float
    reason: str

    def __str__(self) -> str:
        return self.reason


def project_dual_cone(z: np.ndarray, cones: list[tuple[str, int]]) -> np.ndarray:
    """``z`` projected onto ``K*`` for ``cones`` as in :attr:`ConicProgram.cones` (zero →
    free, nonnegative → ``max(z, 0)``, second-order → the projection onto ``{‖x‖ <= t}``)."""
    out = np.array(z, dtype=float, copy=True)
    at = 0
    for kind, m in cones:
        part = out[at:at + m]
        if kind == "nonneg":
            np.maximum(part, 0.0, out=part)
        elif kind == "soc" and m:
            t, norm = part[0], float(np.linalg.norm(part[1:]))
            if norm <= t:
                pass
            elif norm <= -t:
                part[:] = 0.0
            else:
                scale = 0.5 * (t + norm)
                part[1:] *= scale / norm
                part[0] = scale
        at += m
    if at != out.size:
        raise ValueError(f"check_farkas: the cones cover {at} rows, z has {out.size}")
    return out


def check_farkas(A: sp.spmatrix, b: np.ndarray, cones: list[tuple[str, int]],
                 z: np.ndarray | None) -> FarkasCheck:
    """Check ``z`` as a certificate that ``A y + s = b, s ∈ K`` has no solution (module
    docstring): valid if, after projecting ``z`` onto ``K*``, ``bᵀz < 0`` and the radius
    ``−bᵀz / ‖Aᵀz‖₁`` it rules out is at least ``RADIUS_FACTOR · max(1, ‖b‖∞)``."""
    b = np.asarray(b, dtype=float)
    required = RADIUS_FACTOR * max(1.0, float(np.max(np.abs(b), initial=0.0)))
    if z is None or np.size(z) != b.size or not np.all(np.isfinite(z)):
        return FarkasCheck(False, 0.0, required, "no finite certificate of the right size")
    zp = project_dual_cone(np.asarray(z, dtype=float), cones)
    scale = float(np.max(np.abs(zp), initial=0.0))
    if scale == 0.0:
        return FarkasCheck(False, 0.0, required, "the certificate is 0 on the dual cone")
    zp /= scale
    gap = float(b @ zp)
    if not gap < 0.0:
        return FarkasCheck(False, 0.0, required,
                           f"bᵀz = {gap:.3g} is not negative (no contradiction)")
    residual = float(np.abs(sp.csr_matrix(A).T @ zp).sum())
    radius = np.inf if residual == 0.0 else -gap / residual
    words = (f"‖Aᵀz‖₁ = {residual:.2g}, bᵀz = {gap:.3g} (‖z‖∞ = 1 on K*): no feasible point "
             f"with ‖y‖∞ < {radius:.3g}")
    if radius >= required:
        return FarkasCheck(True, radius, required, words)
    return FarkasCheck(False, radius, required, f"{words}, fewer than the {required:.3g} required")
