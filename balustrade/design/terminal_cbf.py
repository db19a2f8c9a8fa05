"""Offline design of terminal CBFs: solve the SDP (6.17)/(7.11) of
:mod:`balustrade.problems.terminal_cbf` on a synthesis target and build the
:class:`~balustrade.problems.terminal_cbf.TerminalCBF` (SPEC §2.27).

The formulation (the SDP itself) lives in ``problems/``, which imports only the language;
solving it needs a backend, so the solve-and-interpret step lives here.
"""

from __future__ import annotations

import warnings

import numpy as np

from balustrade._checks import as_scalar, check_instance
from balustrade.backends import solve_synthesis
from balustrade.dsl.sets import Polytope
from balustrade.errors import BalustradeError, DegenerateResultWarning
from balustrade.problems._args import nonnegative
from balustrade.problems.terminal_cbf import TerminalCBF, terminal_cbf_from, terminal_cbf_sdp


def synthesize_terminal_cbf(A: np.ndarray, B: np.ndarray, X: Polytope, U: Polytope,
                            delta_N: float = 0.0, decrease_factor: float = 0.99,
                            target: object = "sdp", min_level: float = 0.0) -> TerminalCBF:
    """Solve (7.11)/(6.17) (:func:`~balustrade.problems.terminal_cbf.terminal_cbf_sdp`) for
    ``x⁺ = Ax + Bu`` with state rows tightened by ``delta_N`` (``Δ_{N−1}``) and return the
    terminal CBF. ``X``/``U`` may already be tightened by an RPI set (Chapters 5, 6).
    ``decrease_factor`` is ``λ`` in the invariance LMI; ``target`` a synthesis target
    (default: the preset ``"sdp"``).

    ``min_level = γ > 0`` imposes the input LMI on ``b̄_u / sqrt(1 + γ)``, so that
    ``γ_f >= γ`` (``γ_f`` is computed on ``U`` itself). A degenerate ``γ_f ≈ 0`` is
    returned with a :class:`~balustrade.errors.DegenerateResultWarning` naming the
    limiting input rows (see the module docstring)."""
    sdp = terminal_cbf_sdp(A, B, X, U, delta_N, decrease_factor, min_level)
    sol = solve_synthesis(sdp, target)
    if not sol.ok:
        raise BalustradeError(f"terminal CBF SDP: no solution ({sol.status}: {sol.message}); "
                              "the constraints may admit no invariant ellipsoid")
    cbf = terminal_cbf_from(sol.values, U,
                            as_scalar(decrease_factor, "synthesize_terminal_cbf: decrease_factor"),
                            sol.status, sol.solve_time)
    if cbf.degenerate:
        warnings.warn(cbf.degenerate, DegenerateResultWarning, stacklevel=2)
    return cbf


def terminal_cbf_with_domain(A: np.ndarray, B: np.ndarray, X_E: Polytope, U_E: Polytope,
                             delta_N: float, level: float = 1.0,
                             decrease_factor: float = 0.99) -> TerminalCBF:
    """The terminal CBF SDP (6.17) with the input LMI imposed on ``U ⊖ κ(E)`` scaled by
    ``1/sqrt(1 + level)``, so that ``π_f(x) = Kx ∈ U ⊖ κ(E)`` on ``D_f = {h_f <= γ_f}`` with
    ``γ_f >= level`` (SPEC §2.27 [Gap] on ``γ_f``). The printed SDP (``level = 0``) makes the
    ellipsoid touch the input constraint, so ``γ_f ≈ 0`` and ``D_r = {h_r <= α_f γ_f}`` of
    Theorem 5.15 collapses onto ``S_r``; a positive level gives the decrease guarantee a
    region. The ellipsoid stays inside ``X ⊖ E`` and ``U ⊖ κ(E)`` as the thesis requires."""
    level = nonnegative(level, "terminal_cbf_with_domain: level")
    check_instance(U_E, Polytope, "terminal_cbf_with_domain: U_E")
    return synthesize_terminal_cbf(A, B, X_E, U_E, delta_N=delta_N,
                                   decrease_factor=decrease_factor, min_level=level)


__all__ = ["synthesize_terminal_cbf", "terminal_cbf_with_domain"]
