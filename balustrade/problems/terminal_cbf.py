"""Ellipsoidal terminal CBF synthesis, SDP (6.17) / (7.11) (SPEC §2.27).

``min −log det E`` s.t. ``[[λE, (AE+BY)ᵀ], [AE+BY, E]] ⪰ 0`` (invariance with strict
decrease, λ < 1 [Default]; λ = 1 is the printed LMI), ``[[(b̄_x,i − Δ)², a_iᵀE], [E a_i, E]] ⪰ 0``
for every state row and ``[[b̄_u,j², a_jᵀY], [Yᵀa_j, E]] ⪰ 0`` for every input row. Outputs
``P = E⁻¹``, ``K = Y P``, ``h_f(x) = xᵀPx − 1``, ``π_f(x) = Kx`` and
``γ_f = min_j b̄_u,j² / (a_jᵀ K E Kᵀ a_j) − 1``, the largest level with ``Kx ∈ U`` on
``D_f = {h_f <= γ_f}`` (SPEC §2.27 [Default]).

**Degenerate level.** The volume-maximal ellipsoid usually touches an input row: its LMI
is then active, ``a_jᵀKEKᵀa_j = b̄_u,j²``, and ``γ_f = 0`` up to the solver's accuracy —
``D_f`` collapses onto ``S_f = {h_f <= 0}`` and ``D_PB = {h_PB <= α_f γ_f}`` onto ``S_PB``
(Assumption 2.29 needs ``γ_f > 0``).
:func:`~balustrade.design.terminal_cbf.synthesize_terminal_cbf` then warns
(:class:`~balustrade.errors.DegenerateResultWarning`) naming the active input rows, and
records the reason in :attr:`TerminalCBF.degenerate`; ``min_level = γ`` reserves a level
(the input LMI on ``b̄_u / sqrt(1 + γ)``, so ``γ_f >= γ``).
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from balustrade._checks import as_matrix, as_scalar, check_instance, check_psd
from balustrade.dsl.policies import AffinePolicy
from balustrade.dsl.sets import Polytope
from balustrade.dsl.synthesis import SynthesisProblem, bmat, logdet
from balustrade.errors import (
    BalustradeError,
    ShapeError,
    moved_names,
)

#: ``γ_f`` below this is reported as degenerate (it is ``b²/(aᵀKEKᵀa) − 1`` of an active
#: input row: 0 in exact arithmetic, ~1e-10 from an interior-point solver)
DEGENERATE_LEVEL = 1e-6


@dataclass(frozen=True)
class TerminalCBF:
    """``h_f(x) = xᵀPx − 1`` with ``π_f(x) = Kx`` valid on ``D_f = {h_f <= γ_f}``."""

    P: np.ndarray
    K: np.ndarray
    gamma_f: float
    decrease_factor: float = 1.0
    status: str = "optimal"
    solve_time: float = 0.0
    #: input rows of ``U`` attaining the minimum in ``γ_f`` (the rows that bound ``D_f``)
    limiting_rows: tuple[int, ...] = ()
    #: why ``γ_f`` is degenerate (``γ_f`` < :data:`DEGENERATE_LEVEL`), else ``""``
    degenerate: str = ""

    def __call__(self, x: object) -> object:
        """``h_f(x)`` on CasADi symbols or numbers."""
        if isinstance(x, (ca.SX, ca.MX, ca.DM)):
            return ca.mtimes([x.T, ca.DM(self.P), x]) - 1
        x = np.asarray(x, dtype=float).reshape(-1)
        return float(x @ self.P @ x - 1.0)

    @property
    def policy(self) -> AffinePolicy:
        """``π_f(x) = Kx`` as an explicit affine law: called on a state like a function, and
        on CasADi symbols, so a controller built with it emits C that evaluates the same
        expression (:mod:`balustrade.dsl.policies`; session 13)."""
        return AffinePolicy(self.K)

    @property
    def E(self) -> np.ndarray:
        return np.linalg.inv(self.P)


def terminal_cbf_sdp(A: np.ndarray, B: np.ndarray, X: Polytope, U: Polytope,
                     delta_N: float = 0.0, decrease_factor: float = 0.99,
                     min_level: float = 0.0) -> SynthesisProblem:
    """SDP (7.11)/(6.17) for ``x⁺ = Ax + Bu``, written in the synthesis language:

    ``min −log det E`` over ``E = Eᵀ``, ``Y`` s.t. ``[[λE, (AE+BY)ᵀ], [AE+BY, E]] ⪰ 0``,
    ``[[b̄_x,i², a_iᵀE], [Ea_i, E]] ⪰ 0`` (state rows, ``b̄_x = b_x − Δ_{N−1}``) and
    ``[[b̄_u,j², a_jᵀY], [Yᵀa_j, E]] ⪰ 0`` (input rows, ``b̄_u = b_u / sqrt(1 + min_level)``).
    The blocks are named ``invariance``, ``state row i``, ``input row j``."""
    A, B, bx, bu, decrease_factor = _checked(A, B, X, U, delta_N, decrease_factor, min_level)
    n, m = B.shape
    sdp = SynthesisProblem("terminal CBF SDP (7.11)")
    E = sdp.matrix("E", (n, n), symmetric=True)
    Y = sdp.matrix("Y", (m, n))
    AEBY = A @ E + B @ Y
    sdp.lmi("invariance", bmat([[decrease_factor * E, AEBY.T], [AEBY, E]]))
    for i, (a, b) in enumerate(zip(X.H, bx)):
        sdp.lmi(f"state row {i}", bmat([[b ** 2, a[None] @ E], [(a[None] @ E).T, E]]))
    for j, (a, b) in enumerate(zip(U.H, bu)):
        sdp.lmi(f"input row {j}", bmat([[b ** 2, a[None] @ Y], [(a[None] @ Y).T, E]]))
    sdp.minimize(-logdet(E))
    return sdp


def _checked(A: object, B: object, X: object, U: object, delta_N: object,
             decrease_factor: object, min_level: object
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """The checked data of (7.11): ``A``, ``B``, state bounds ``b_x − Δ``, input bounds
    ``b_u / sqrt(1 + γ)`` and ``λ``; errors name the argument."""
    check_instance(X, Polytope, "terminal CBF SDP: X")
    check_instance(U, Polytope, "terminal CBF SDP: U")
    delta_N = as_scalar(delta_N, "terminal CBF SDP: delta_N (Δ_{N−1})", low=0.0)
    min_level = as_scalar(min_level, "terminal CBF SDP: min_level", low=0.0)
    decrease_factor = as_scalar(decrease_factor, "terminal CBF SDP: decrease factor λ",
                                low=0.0, high=1.0, low_open=True)
    A = as_matrix(A, "terminal CBF SDP: A")
    n = A.shape[0]
    if A.shape != (n, n):
        raise ShapeError("terminal CBF SDP: A", (n, n), A.shape)
    B = as_matrix(B, "terminal CBF SDP: B", (n, None))
    m = B.shape[1]
    if X.dim != n or U.dim != m:
        raise ShapeError("terminal CBF SDP: sets", f"X of dim {n}, U of dim {m}",
                         f"X of dim {X.dim}, U of dim {U.dim}", what="")
    bx = X.h - delta_N
    if np.any(bx <= 0) or np.any(U.h <= 0):
        raise BalustradeError("terminal CBF SDP: the origin must lie in the interior of the "
                              f"(tightened) constraints; state bounds {bx}, input bounds {U.h}")
    return A, B, bx, U.h / np.sqrt(1.0 + min_level), decrease_factor


def terminal_cbf_from(values: dict[str, np.ndarray], U: Polytope, decrease_factor: float,
                      status: str = "optimal", solve_time: float = 0.0) -> TerminalCBF:
    """The terminal CBF of a solution ``{"E", "Y"}`` of (7.11): ``P = E⁻¹``, ``K = YP`` and
    ``γ_f`` on ``U`` with its limiting rows (degenerate reason, no warning)."""
    Ev = 0.5 * (values["E"] + values["E"].T)
    if not np.all(np.isfinite(Ev)) or np.min(np.linalg.eigvalsh(Ev)) <= 0:
        raise BalustradeError(f"terminal CBF SDP: the solver returned a singular ellipsoid "
                              f"(eigenvalues of E {np.linalg.eigvalsh(Ev)}); the constraints "
                              "may admit no invariant ellipsoid with nonempty interior")
    P = np.linalg.inv(Ev)
    P = 0.5 * (P + P.T)
    K = values["Y"] @ P
    levels = input_levels(P, K, U)
    gamma_f = float(np.min(levels)) if levels.size else float("inf")
    limiting = tuple(int(j) for j in np.flatnonzero(levels <= gamma_f + DEGENERATE_LEVEL))
    reason = _degenerate_reason(gamma_f, limiting, U) if gamma_f < DEGENERATE_LEVEL else ""
    return TerminalCBF(P=P, K=K, gamma_f=gamma_f, decrease_factor=decrease_factor,
                       status=status, solve_time=solve_time, limiting_rows=limiting,
                       degenerate=reason)


def _row_text(a: np.ndarray, b: float) -> str:
    """``a_jᵀu <= b_j`` as text, e.g. ``-u_0 <= 5``."""
    text = ""
    for i, c in enumerate(a):
        if c == 0:
            continue
        sign = "-" if c < 0 else ("+" if text else "")
        text += f"{' ' if text else ''}{sign}{'' if abs(c) == 1 else f'{abs(c):g}·'}u_{i}"
    return f"{text or '0'} <= {b:g}"


def _degenerate_reason(gamma_f: float, rows: tuple[int, ...], U: Polytope) -> str:
    """Why ``γ_f`` vanishes: the input rows whose LMI is active at the SDP solution."""
    names = " and ".join(f"{j} ({_row_text(U.H[j], float(U.h[j]))})" for j in rows)
    plural = "s" if len(rows) > 1 else ""
    verb = "are" if len(rows) > 1 else "is"
    return (f"terminal CBF SDP: degenerate level gamma_f = {gamma_f:.3g} (Assumption 2.29 "
            f"needs gamma_f > 0): the LMI{plural} of input row{plural} {names} of "
            f"{U.name!r} {verb} active at the SDP solution (b_j^2 = a_j^T K E K^T a_j) — the "
            "volume-maximal ellipsoid is input-limited: pi_f(x) = Kx reaches that input "
            "bound on the boundary of S_f = {h_f <= 0} itself, so D_f = {h_f <= gamma_f} "
            "collapses onto S_f and D_PB = {h_PB <= alpha_f gamma_f} onto S_PB. Pass "
            "min_level=gamma > 0 (input LMI on b_u / sqrt(1 + gamma)) to reserve a level")


def input_levels(P: np.ndarray, K: np.ndarray, U: Polytope) -> np.ndarray:
    """``b_u,j² / (a_jᵀ K P⁻¹ Kᵀ a_j) − 1`` for every input row ``j`` (``+inf`` for a row
    ``K`` does not reach): the level at which ``Kx`` meets row ``j``."""
    check_instance(U, Polytope, "input_levels: U")
    P = check_psd(P, "input_levels: P", strict=True)
    K = as_matrix(K, "input_levels: K", (U.dim, P.shape[0]))
    E = np.linalg.inv(P)
    levels = []
    for a, b in zip(U.H, U.h):
        s = float(a @ K @ E @ K.T @ a)
        levels.append(np.inf if s <= 0 else b ** 2 / s - 1.0)
    return np.asarray(levels, dtype=float)


def largest_level(P: np.ndarray, K: np.ndarray, U: Polytope) -> float:
    """``γ_f = min_j b_u,j² / (a_jᵀ K P⁻¹ Kᵀ a_j) − 1``: the largest ``γ`` with ``Kx ∈ U``
    on ``{xᵀPx − 1 <= γ}`` (SPEC §2.27 [Default])."""
    levels = input_levels(P, K, U)
    return float(np.min(levels)) if levels.size else float("inf")

#: names that moved out of this module (issue #13): deprecated aliases (errors.moved_names)
__getattr__ = moved_names(__name__, {
    "synthesize_terminal_cbf": "balustrade.design.terminal_cbf",
})
