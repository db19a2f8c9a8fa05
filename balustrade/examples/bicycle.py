"""The kinematic bicycle example (thesis Section 8.2, SPEC §2.31): robust PCBF ingredients.

:func:`bicycle_design` builds them around the operating point ``x_s = (0, 0, 1.1, 0)``.
The model itself is :mod:`balustrade.models.bicycle`.

``method="incremental"`` (default): the error set ``E = {eᵀPe <= 1}`` and ``κ(e) = Ke`` of an
incremental quadratic Lyapunov function over the polytopic bound of *all* Jacobians
(:func:`balustrade.design.incremental_rpi.incremental_rpi`, Claim 1 there: RPI for the
nonlinear error dynamics), and the terminal CBF ``h_f(x) = (x − x_s)ᵀP_f(x − x_s) − 1``,
``π_f(x) = K_f(x − x_s)`` of (6.17) with the invariance LMI at every Jacobian vertex
(:func:`~balustrade.design.incremental_rpi.robust_terminal_cbf`, Claim 2: ``{h_f <= 0}``
invariant for the nonlinear nominal model). The Jacobian bound is taken on the domain
``D = ℝ × ([ψ, v, δ bounds of X] ⊕ [−a, a])`` with ``a`` the semi-axes of ``E`` along
``ψ, v, δ``, found by a fixed-point iteration (design on ``D``, enlarge ``D`` by the new
``E``'s semi-axes, until they no longer grow): then every nominal state ``z ∈ X`` and true
state ``x = z + e``, ``e ∈ E``, lie in ``D``, so the guarantee covers all of ``X`` (any
``p_y``: the Jacobian does not depend on it). The domain used is recorded in
``design.error.info["domain"]``.

``method="linearization"``: the earlier design, kept for comparison — ``E`` from the
ellipsoidal RPI SDP on the linearization at ``x_s`` and the terminal CBF of (6.17) on the
same linearization. It is a *linearization-only* design: the sampled check
(:func:`nonlinear_rpi_margin`, or :func:`~balustrade.design.incremental_rpi.
sampled_rpi_check`) finds that its ``E`` is *not* RPI for the nonlinear model (margin about
0.26 over ``z ∈ X``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from balustrade._checks import as_scalar, check_horizon
from balustrade.design.incremental_rpi import (
    PolytopicLDI,
    TerminalSpec,
    incremental_rpi,
    robust_terminal_cbf,
)
from balustrade.design.rpi import ellipsoidal_rpi
from balustrade.design.terminal_cbf import terminal_cbf_with_domain
from balustrade.dsl.error_sets import ErrorSet
from balustrade.dsl.policies import AffinePolicy
from balustrade.dsl.sets import Box, Polytope
from balustrade.dsl.system import System
from balustrade.errors import BalustradeError
from balustrade.models.bicycle import (
    V_S,
    ShiftedCBF,
    bicycle,
    bicycle_sets,
    input_matrix,
    jacobian_ldi,
)

METHODS = ("incremental", "linearization")
#: the disturbance enters the heading
G_HEADING = np.array([[0.0], [1.0], [0.0], [0.0]])
#: λ values of the incremental design's line search (a wider search, 0.05…0.95 and 0.97…0.99,
#: picked 0.95 on every domain of the fixed-point iteration)
LAMBDAS = (0.93, 0.95, 0.97)
#: each iteration enlarges D by this factor times the semi-axes of E (overshoot: fewer SDPs)
PAD_FACTOR = 1.1
#: smallest semi-axes of E along (p_y, ψ, v, δ): v is undisturbed and dead-beat controlled,
#: its axis would collapse (P_vv ≈ 5e8) and slow the horizon solvers down
MIN_AXES = (1e-3, 1e-3, 0.005, 1e-3)
#: decrease factor λ_f of the terminal invariance LMI
DECREASE_F = 0.99


@dataclass
class BicycleDesign:
    system: System
    X: Box
    U: Box
    W: Box
    error: ErrorSet
    cbf: ShiftedCBF
    N: int
    deltas: np.ndarray
    alpha_f: float = 1e6
    method: str = "incremental"
    ldi: PolytopicLDI | None = None
    info: dict = field(default_factory=dict)

    @property
    def X_E(self) -> Polytope:
        return self.error.tighten_state(self.X)

    @property
    def U_E(self) -> Polytope:
        return self.error.tighten_input(self.U)

    @property
    def pi_f(self) -> AffinePolicy:
        """The terminal policy ``π_f(x) = K_f (x − x_s)`` of ``cbf`` as an explicit affine
        law: the controllers of Algorithms 5.2/6.4 and their emitted C evaluate the same
        expression (the same law as ``cbf.policy``; session 13)."""
        return AffinePolicy(self.cbf.K, x_s=self.cbf.x_s)

    def terminal_spec(self) -> TerminalSpec:
        """What :func:`~balustrade.design.incremental_rpi.sampled_terminal_check` and
        :func:`~balustrade.design.incremental_rpi.worst_case_terminal_check` need."""
        return TerminalSpec(self.cbf.P, self.cbf.K, self.cbf.x_s, self.X_E, self.U_E,
                            float(self.deltas[-1]), DECREASE_F)


def bicycle_ldi(pad: np.ndarray | None = None) -> PolytopicLDI:
    """The polytopic bound of the bicycle's Jacobians on ``ℝ × ([ψ, v, δ] of X ⊕ [−pad,
    pad])`` (``pad`` over ``(ψ, v, δ)``, default 0)."""
    X, _, _ = bicycle_sets()
    pad = np.zeros(3) if pad is None else np.asarray(pad, dtype=float).reshape(3)
    lo = np.r_[-np.inf, X.lb[1:] - pad]
    hi = np.r_[np.inf, X.ub[1:] + pad]
    A0, dirs, intervals = jacobian_ldi(lo, hi)
    return PolytopicLDI(A0, tuple(dirs), intervals, input_matrix(), Box(lo, hi, name="D"))


def _incremental_error(X: Box, U: Box, W: Box, x_s: np.ndarray, iterations: int = 8
                       ) -> tuple[ErrorSet, PolytopicLDI]:
    """The fixed point of the module docstring: ``D`` covers ``X ⊕ E`` in ``(ψ, v, δ)``."""
    pad = np.zeros(3)
    for _ in range(iterations):
        ldi = bicycle_ldi(pad)
        error = incremental_rpi(ldi, W, X, U, G_HEADING, x_s, lambdas=LAMBDAS, name="E_bicycle",
                                min_axes=MIN_AXES)
        axes = np.sqrt(np.diag(np.linalg.inv(error.E.P)))[1:]
        if np.all(axes <= pad + 1e-9):
            error.info["domain_covers_X_plus_E"] = True
            error.info["pad_psi_v_delta"] = pad.tolist()
            return error, ldi
        pad = np.maximum(pad, axes * PAD_FACTOR)
    raise BalustradeError(f"bicycle_design: the Jacobian domain did not settle in {iterations} "
                          f"iterations (pad {pad.tolist()})")


@lru_cache(maxsize=8)
def _cached(N: int, delta_step: float, method: str) -> BicycleDesign:
    system = bicycle()
    X, U, W = bicycle_sets()
    x_s = np.array([0.0, 0.0, V_S, 0.0])
    deltas = delta_step * np.arange(N)
    if method == "incremental":
        error, ldi = _incremental_error(X, U, W, x_s)
        cbf = robust_terminal_cbf(ldi, error.tighten_state(X), error.tighten_input(U), x_s,
                                  delta_N=float(deltas[-1]), level=1.0,
                                  decrease_factor=DECREASE_F)
    else:
        ldi = None
        A, B = system.jacobians(x_s, np.zeros(2))
        Xs = Polytope(X.H, X.h - X.H @ x_s, name="X_lane-x_s")
        error = ellipsoidal_rpi(A, B, W, Xs, U, G=G_HEADING, name="E_bicycle")
        error.info["method"] += " on the linearization at x_s (linearization-only)"
        X_E, U_E = error.tighten_state(Xs), error.tighten_input(U)
        cbf = terminal_cbf_with_domain(A, B, X_E, U_E, deltas[-1], level=1.0)
    return BicycleDesign(system, X, U, W, error, ShiftedCBF(cbf.P, cbf.K, x_s, cbf.gamma_f),
                         N, deltas, method=method, ldi=ldi)


def bicycle_design(N: int = 20, delta_step: float = 1e-4, method: str = "incremental"
                   ) -> BicycleDesign:
    """The robust PCBF ingredients of §8.2 (module docstring): ``N``, ``Δ_i = i·delta_step``,
    ``method`` ``"incremental"`` (default, RPI for the nonlinear model) or
    ``"linearization"`` (the earlier, linearization-only design). Cached per arguments
    (the SDPs take seconds); treat the result as read-only."""
    if method not in METHODS:
        raise BalustradeError(f"bicycle_design: method must be one of {METHODS}, got "
                              f"{method!r}")
    # N = 0 used to end in an IndexError, N = 2.5 was silently truncated to 2; Δ_i must
    # increase strictly (SPEC §1.4), so delta_step > 0 (audit D, session 15)
    N = check_horizon(N, "bicycle_design")
    delta_step = as_scalar(delta_step, "bicycle_design: delta_step", low=0.0, low_open=True)
    return _cached(N, delta_step, method)


def nonlinear_rpi_margin(design: BicycleDesign, samples: int = 2000, seed: int = 0) -> float:
    """Sampled ``max c_E(e⁺)`` of the nominal-vs-true error ``e⁺ = f(z + e, v + Ke, w) −
    f(z, v, 0)`` over ``z ∈ X``, ``v ∈ U ⊖ KE``, ``e ∈ ∂E``, ``w ∈ W`` (<= 0: no counterexample)."""
    rng = np.random.default_rng(seed)
    d = design
    E, K = d.error.E, d.error.K
    U_E = d.error.tighten_input(d.U)
    f = d.system.function
    worst = -np.inf
    zs = d.X.sample(samples, rng)
    vs = U_E.sample(samples, rng)
    es = E.sample(samples, rng)
    es /= np.sqrt(np.einsum("ij,jk,ik->i", es, E.P, es))[:, None]
    ws = d.W.sample(samples, rng)
    for z, v, e, w in zip(zs, vs, es, ws):
        e_next = np.asarray(f(z + e, v + K @ e, w, np.zeros(0))).reshape(-1) - \
            np.asarray(f(z, v, np.zeros(1), np.zeros(0))).reshape(-1)
        worst = max(worst, float(e_next @ E.P @ e_next - 1.0))
    return worst
