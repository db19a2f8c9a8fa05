"""Ellipsoidal RPI error set and its feedback by SDP (Assumption 5.13, SPEC §1.11 [Default]).

For ``e⁺ = (A + BK) e + G w``, ``w ∈ W``, the ellipsoid ``E = {eᵀ E_P⁻¹ e <= 1}`` with the
feedback ``κ(e) = K e``, ``Y = K E_P``, is RPI when for a ``λ ∈ (0, 1)`` and every vertex
``w^v`` of ``W``

    ``[[λE_P, 0, (AE_P+BY)ᵀ], [0, 1−λ, (Gw^v)ᵀ], [AE_P+BY, Gw^v, E_P]] ⪰ 0``   (S-procedure).

Among them :func:`rpi_sdp` minimizes the sum of the squared *relative* tightenings of all
constraint rows, ``Σ_j [A_x]_j E_P [A_x]_jᵀ / [b_x]_j² + Σ_j t_u,j / [b_u]_j²`` with the
epigraph LMIs ``[[t_u,j, [A_u]_j Y], [Yᵀ[A_u]_jᵀ, E_P]] ⪰ 0`` (``h_{KE}([A_u]_j)² <= t_u,j``).
``λ`` is a parameter of the compiled SDP; :func:`~balustrade.design.rpi.ellipsoidal_rpi`
line-searches it.
"""

from __future__ import annotations

import numpy as np

from balustrade._checks import as_matrix, check_instance
from balustrade.dsl.error_sets import bounded_vertices
from balustrade.dsl.sets import Polytope, Set
from balustrade.dsl.synthesis import SynthesisProblem, bmat
from balustrade.errors import BalustradeError, ShapeError, moved_names


def rpi_sdp(A: np.ndarray, B: np.ndarray, W: Set, X: Polytope, U: Polytope,
            G: np.ndarray | None = None) -> SynthesisProblem:
    """The RPI SDP of SPEC §1.11 with ``λ`` as the parameter ``"lambda"`` (variables
    ``E``, ``Y``, ``t_u``; blocks ``E > 0``, ``vertex v``, ``input row j``)."""
    A, B, G = _checked(A, B, W, X, U, G)
    n, m = B.shape
    for S in (X, U):
        if np.any(S.h <= 0):
            raise BalustradeError(f"RPI SDP: the origin must be inside {S.name} (row bound "
                                  f"{S.h[S.h <= 0][0]})")
    sdp = SynthesisProblem("ellipsoidal RPI SDP (SPEC §1.11)")
    E = sdp.matrix("E", (n, n), symmetric=True)
    Y = sdp.matrix("Y", (m, n))
    t_u = sdp.vector("t_u", U.H.shape[0])
    lam = sdp.parameter("lambda", nonneg=True)
    AEBY = A @ E + B @ Y
    sdp.lmi("E > 0", E >> 1e-9 * np.eye(n))
    for v, w in enumerate(bounded_vertices(W) @ G.T):
        wc = w.reshape(n, 1)
        sdp.lmi(f"vertex {v}", bmat([[lam * E, np.zeros((n, 1)), AEBY.T],
                                     [np.zeros((1, n)), 1 - lam, wc.T],
                                     [AEBY, wc, E]]))
    for j, a in enumerate(U.H):
        sdp.lmi(f"input row {j}", bmat([[t_u[j], a[None] @ Y], [(a[None] @ Y).T, E]]))
    sdp.minimize(sum([(a @ E @ a) / b ** 2 for a, b in zip(X.H, X.h)]
                     + [t_u[j] / b ** 2 for j, b in enumerate(U.h)]))
    return sdp


def _checked(A: object, B: object, W: object, X: object, U: object, G: object
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    A = as_matrix(A, "RPI SDP: A")
    n = A.shape[0]
    if A.shape != (n, n):
        raise ShapeError("RPI SDP: A", "a square matrix", A.shape)
    B = as_matrix(B, "RPI SDP: B", (n, None))
    m = B.shape[1]
    check_instance(W, Set, "RPI SDP: W")
    check_instance(X, Polytope, "RPI SDP: X")
    check_instance(U, Polytope, "RPI SDP: U")
    G = np.eye(n) if G is None else as_matrix(G, "RPI SDP: G", (n, W.dim))
    if G.shape[1] != W.dim:
        raise ShapeError(f"RPI SDP: W ({W.name})", f"dimension {G.shape[1]}",
                         f"dimension {W.dim}")
    if X.dim != n or U.dim != m:
        raise ShapeError("RPI SDP: sets", f"X of dim {n}, U of dim {m}",
                         f"X of dim {X.dim}, U of dim {U.dim}", what="")
    return A, B, G


__all__ = ["rpi_sdp"]

#: names that moved out of this module (issue #13): deprecated aliases (errors.moved_names)
__getattr__ = moved_names(__name__, {
    "ellipsoidal_rpi": "balustrade.design.rpi",
})
