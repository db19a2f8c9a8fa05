"""Formulations of the nonlinear RPI design (thesis §6.5, §8.2; SPEC §2.31): a polytopic bound
of a model's Jacobians (:class:`PolytopicLDI`), the SDP of an incremental quadratic Lyapunov
function with linear error feedback over it (:func:`incremental_rpi_sdp`, Claim 1 of
:mod:`balustrade.design.incremental_rpi`) and the terminal-CBF SDP (6.17) over the same bound
(:func:`robust_terminal_cbf_sdp`, Claim 2). The claims, their proofs, the solves and the checks
are in :mod:`balustrade.design.incremental_rpi`."""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from balustrade._checks import as_matrix, check_instance
from balustrade.dsl.error_sets import bounded_vertices
from balustrade.dsl.sets import Box, Polytope, Set
from balustrade.dsl.synthesis import SynthesisProblem, bmat, logdet
from balustrade.errors import BalustradeError, ShapeError


@dataclass(frozen=True)
class PolytopicLDI:
    """``∂f/∂x ∈ conv{A0 + Σ_k a_k E_k : a_k ∈ {lo_k, hi_k}}``, ``∂f/∂u = B`` on ``domain``
    (a box of states; the claims of the module docstring hold for segments inside it)."""

    A0: np.ndarray
    directions: tuple[np.ndarray, ...]
    intervals: np.ndarray
    B: np.ndarray
    domain: Box

    def __post_init__(self) -> None:
        n = self.A0.shape[0]
        if self.A0.shape != (n, n) or any(E.shape != (n, n) for E in self.directions):
            raise ShapeError("PolytopicLDI: A0 and directions", f"({n}, {n}) matrices",
                             [self.A0.shape, *(E.shape for E in self.directions)])
        if self.intervals.shape != (len(self.directions), 2):
            raise ShapeError("PolytopicLDI: intervals", (len(self.directions), 2),
                             self.intervals.shape)
        if np.any(self.intervals[:, 0] > self.intervals[:, 1]):
            raise BalustradeError(f"PolytopicLDI: intervals: a lower end exceeds an upper end "
                                  f"({self.intervals.tolist()})")
        if self.B.shape[0] != n or self.domain.dim != n:
            raise ShapeError("PolytopicLDI: B, domain", f"{n} rows / dimension {n}",
                             (self.B.shape, self.domain.dim))

    def vertices(self) -> list[np.ndarray]:
        """The ``2^K`` matrices at the corners of the interval box (duplicates removed)."""
        out: list[np.ndarray] = []
        for corner in itertools.product(*self.intervals.tolist()):
            A = self.A0 + sum(c * E for c, E in zip(corner, self.directions))
            if not any(np.array_equal(A, B) for B in out):
                out.append(A)
        return out

    def describe_domain(self) -> dict:
        return {"lb": self.domain.lb.tolist(), "ub": self.domain.ub.tolist(),
                "intervals": self.intervals.tolist(), "vertices": len(self.vertices())}


def incremental_rpi_sdp(ldi: PolytopicLDI, W: Set, X: Polytope, U: Polytope,
                        G: np.ndarray, min_axes: object = 1e-3) -> SynthesisProblem:
    """The SDP of Claim 1 (module docstring) with ``λ`` as the parameter ``"lambda"``: one
    LMI block ``vertex i, w j`` per Jacobian vertex and disturbance vertex; objective the sum
    of squared relative tightenings of the rows of ``X`` and ``U`` (centred at the operating
    point: their ``h`` must be positive). ``E_P ⪰ diag(min_axes²)`` (a scalar or one entry per
    state) makes ``E`` contain the axis-aligned ellipsoid with these semi-axes: an
    undisturbed, dead-beat-controlled direction (the bicycle's ``v``) would otherwise
    collapse and make ``P = E_P⁻¹`` ill-conditioned for the horizon solvers (``P_vv ≈ 5e8``
    for the bicycle without it)."""
    check_instance(W, Set, "incremental_rpi_sdp: W")
    check_instance(X, Polytope, "incremental_rpi_sdp: X")
    check_instance(U, Polytope, "incremental_rpi_sdp: U")
    n, m = ldi.B.shape
    G = as_matrix(G, "incremental_rpi_sdp: G", (n, W.dim))
    for S in (X, U):
        if np.any(S.h <= 0):
            raise BalustradeError(f"incremental_rpi_sdp: the operating point must be inside "
                                  f"{S.name} (row bounds {S.h.tolist()})")
    sdp = SynthesisProblem("incremental RPI SDP over a polytopic LDI (§6.5, §8.2)")
    E = sdp.matrix("E", (n, n), symmetric=True)
    Y = sdp.matrix("Y", (m, n))
    t_u = sdp.vector("t_u", U.H.shape[0])
    lam = sdp.parameter("lambda", nonneg=True)
    axes = np.broadcast_to(np.asarray(min_axes, dtype=float), (n,))
    if np.any(axes <= 0):
        raise BalustradeError(f"incremental_rpi_sdp: min_axes must be positive, got {axes}")
    sdp.lmi("E > min_axes", E >> np.diag(axes ** 2))
    ws = bounded_vertices(W) @ G.T
    for i, A in enumerate(ldi.vertices()):
        AEBY = A @ E + ldi.B @ Y
        for j, w in enumerate(ws):
            wc = w.reshape(n, 1)
            sdp.lmi(f"vertex {i}, w {j}", bmat([[lam * E, np.zeros((n, 1)), AEBY.T],
                                                 [np.zeros((1, n)), 1 - lam, wc.T],
                                                 [AEBY, wc, E]]))
    for j, a in enumerate(U.H):
        sdp.lmi(f"input row {j}", bmat([[t_u[j], a[None] @ Y], [(a[None] @ Y).T, E]]))
    sdp.minimize(sum([(a @ E @ a) / b ** 2 for a, b in zip(X.H, X.h)]
                     + [t_u[j] / b ** 2 for j, b in enumerate(U.h)]))
    return sdp


def robust_terminal_cbf_sdp(ldi: PolytopicLDI, HX: np.ndarray, bx: np.ndarray,
                            HU: np.ndarray, bu: np.ndarray,
                            decrease_factor: float = 0.99) -> SynthesisProblem:
    """The SDP of Claim 2 (:mod:`balustrade.design.incremental_rpi`): (6.17) with the
    invariance LMI at every Jacobian vertex, state rows ``HX e <= bx`` and input rows
    ``HU u <= bu`` (both about the operating point), ``min −log det E``."""
    n, m = ldi.B.shape
    sdp = SynthesisProblem("terminal CBF SDP (6.17) over a polytopic LDI")
    E = sdp.matrix("E", (n, n), symmetric=True)
    Y = sdp.matrix("Y", (m, n))
    for i, A in enumerate(ldi.vertices()):
        AEBY = A @ E + ldi.B @ Y
        sdp.lmi(f"invariance {i}", bmat([[decrease_factor * E, AEBY.T], [AEBY, E]]))
    for i, (a, b) in enumerate(zip(np.atleast_2d(HX), bx)):
        sdp.lmi(f"state row {i}", bmat([[b ** 2, a[None] @ E], [(a[None] @ E).T, E]]))
    for j, (a, b) in enumerate(zip(np.atleast_2d(HU), bu)):
        sdp.lmi(f"input row {j}", bmat([[b ** 2, a[None] @ Y], [(a[None] @ Y).T, E]]))
    sdp.minimize(-logdet(E))
    return sdp


__all__ = ["PolytopicLDI", "incremental_rpi_sdp", "robust_terminal_cbf_sdp"]
