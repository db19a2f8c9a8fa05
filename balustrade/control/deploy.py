"""Typed deployment specs: what a controller hands to an emitter of C.

Each closed-loop controller meant to run on a device answers ``deployment_spec()`` with one
of these frozen dataclasses, holding exactly what the emitted step needs: its compiled
problems, the box of the projected-proposal fallback, tolerances and the algorithm's
constants. :mod:`balustrade.codegen` reads nothing else from a controller, so a controller
can rename or restructure its internals without breaking the C it deploys (and
:mod:`balustrade.control` never imports :mod:`balustrade.codegen`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from balustrade.backends import Compiled
from balustrade.dsl.sets import Polytope, Set
from balustrade.dsl.system import System


@dataclass(frozen=True)
class PCBFDeployment:
    """The PCBF safety filter (Section 2.4): per step the slack problem (2.24), then the
    filter (2.23) with the slacks fixed, with the fallbacks of
    :class:`~balustrade.control.pcbf.PCBFSafetyFilter`."""

    #: (2.24): ``h_PB(x_k)`` and the slacks ``ξ*`` (parameter ``x0``; variables ``u``,
    #: ``xi``, ``xi_N``)
    slack: Compiled
    #: (2.23) with the slacks fixed (parameters ``x0``, ``u_p``, ``xi``, ``xi_N``;
    #: variable ``u``)
    filter: Compiled
    #: input set: the projected-proposal fallback clips ``u_p`` to it
    U: Set
    #: the tightening ``ε`` of (2.23) (built into ``filter``; recorded in the manifest)
    eps: float
    #: a merely feasible (2.24) point of cost ``<= zero_tol`` is optimal (``h_PB >= 0``)
    zero_tol: float
    #: whether the step certifies ``h_PB = 0`` by the shifted plan
    #: (:mod:`balustrade.control.shifted`; the filter's ``shifted_certificate``)
    shifted_certificate: bool = True
    #: whether the step checks that certificate before (2.24) and skips the solve when it
    #: certifies ``h_PB = 0`` (the filter's ``certificate_first``; on by default as in the
    #: filter; without the certificate the emitter turns it off)
    certificate_first: bool = True
    #: whether a certified step's failed (2.23) attempt from its last solution is tried
    #: once more from the certified shifted plan before the cold retries (the filter's
    #: ``shifted_retry``; opt-in, off by default; needs ``certificate_first``)
    shifted_retry: bool = False
    #: which solver of the (2.23) chain makes that attempt: 0 the first, ``k`` the
    #: ``k``-th retry's, ``-1`` the last (the filter's ``shifted_retry_solver``)
    shifted_retry_solver: int = 0


@dataclass(frozen=True)
class ApproximateDeployment:
    """Algorithm 7.5 (Section 7.3): the certification shortcut (line 4), the maximal
    decrease (7.6) by screened multi-start, the filter (7.5), with the fallbacks of
    :class:`~balustrade.control.approximate.ApproximatePCBFFilter`."""

    #: (7.6): the maximal decrease of ``ĥ`` (parameter ``x0``; variable ``u``)
    decrease: Compiled
    #: (7.5) (parameters ``x0``, ``u_p``, ``dh``, ``rho``; variable ``u``)
    filter: Compiled
    #: input set (a box for C: candidates and the fallback are clipped to it)
    U: Set
    #: the model ``x+ = f(x, u)`` (for ``ĥ(f(x, u))``)
    system: System
    #: ``ĥ``, a function of ``x`` on CasADi symbols
    h: Callable
    #: the screening grid over ``U`` (rows), after the candidates ``clip(0)``, ``clip(u_p)``
    grid: np.ndarray = field(repr=False)
    #: local (7.6) solves from the best distinct screened candidates
    n_local: int
    #: ``ρ`` of (7.5)
    rho: float
    #: line 4 of Algorithm 7.5 enabled
    certify: bool
    #: apply ``u_p`` when it meets the decrease of (7.5) (its exact minimizer)
    exact_shortcut: bool
    #: the network ``ĥ`` is made of (``weights``, ``biases``, ``mean``, ``scale``,
    #: ``output_transform``: a :class:`~balustrade.learn.train.MLPModel`), or ``None``; the
    #: emitted C then evaluates ``ĥ`` from its weights in loops (bal/approx_net.c)
    network: object | None = None


@dataclass(frozen=True)
class GridDeployment:
    """Algorithm 8.7 (SPEC §2.34): ``ĥ(f(x, u_i))`` on the rate-limited input grid around
    ``u_{k−1}``, no solver, with the fallbacks of
    :class:`~balustrade.control.approximate.GridPCBFFilter`."""

    #: the model ``x+ = f(x, u)`` (for ``ĥ(f(x, u))``)
    system: System
    #: input set (a box for C: candidates are clipped to it)
    U: Set
    #: ``ĥ``, a CasADi Function of ``x``
    h: Callable
    #: the offsets ``j·Δu`` (rows, ``itertools.product`` order) added to ``u_{k−1}``
    offsets: np.ndarray = field(repr=False)
    #: the input ranges dividing ``u_i − u_p`` in the distance to the proposal
    scale: np.ndarray = field(repr=False)
    #: ``ρ`` of the decrease ``ĥ(f(x, u_i)) <= ρ ĥ(x)``
    rho: float
    #: ``u_{−1}`` before projection onto ``U`` (``reset()`` restores ``Π_U(u_init)``)
    u_init: np.ndarray = field(repr=False)


@dataclass(frozen=True)
class ProblemsDeployment:
    """A controller whose closed-loop step has no emitted C (yet): its compiled problems by
    name, each emittable on its own (:func:`balustrade.codegen.emit_problem`), and the
    algorithm that combines them."""

    problems: dict[str, Compiled]
    algorithm: str


@dataclass(frozen=True)
class TubeDeployment(ProblemsDeployment):
    """What the tube-based steps of Algorithms 5.2 and 6.4 (Chapters 5 and 6) share: the
    applied ``u = v₀ + K(x − z₀)`` (5.16), the candidate (5.17)/(6.14) built from
    ``(z, v, ξ)``, the slacks' ``h̃`` (SPEC §1.12) and the projected-proposal fallback.
    ``problems["slack"]`` is (5.15) (parameter ``x0``; variables ``z``, ``v``, ``xi``,
    ``xi_N``)."""

    #: the model ``x+ = f(x, u, w)`` (the candidate's last state, ``w = 0``)
    system: System
    #: ``X ⊖ E`` (its rows give the minimal slacks and the candidate's last slack)
    X_E: Polytope
    #: input set of the projected-proposal fallback (a box for C)
    U: Set
    #: ``U ⊖ κ(E)``: where the candidate's terminal input must lie (5.17)
    U_E: Polytope
    #: ``h_f`` (callable on CasADi symbols) and ``π_f``
    h_f: Callable
    pi_f: Callable
    #: the linear error feedback ``κ(e) = K e`` (``None``: a user's nonlinear κ)
    K: np.ndarray | None = field(repr=False)
    #: the tightenings ``Δ_i`` (one per step)
    deltas: np.ndarray = field(repr=False)
    #: ``α_f`` of ``h̃`` (SPEC §1.12)
    alpha_f: float


@dataclass(frozen=True)
class RobustDeployment(TubeDeployment):
    """Algorithm 5.2 (Section 5.5): (5.15) then (5.16) with the polished slacks fixed, the
    applied ``u = v₀ + K(x − z₀)``, the candidate (5.17) and the fallbacks of
    :class:`~balustrade.control.robust.RobustPCBFSafetyFilter`. ``problems`` holds
    ``"slack"`` (5.15) and ``"filter"`` (5.16) (parameters ``x0``, ``u_p``, ``xi``,
    ``xi_N``; variables ``z``, ``v``), so :func:`balustrade.codegen.emit_problems` still
    emits them one by one."""

    #: the slack norm of ``h̃`` (SPEC §1.12)
    slack_norm: int | float
    #: the recovery target (a preset name or Target; ``None``: none) whose attempt leads
    #: the (5.15) chain on a recovery step (:mod:`balustrade.backends.recovery`)
    recovery_target: object = None


@dataclass(frozen=True)
class MultiobjectiveDeployment(TubeDeployment):
    """Algorithm 6.4 (Section 6.4): (5.15) once for the first candidate, then per step
    (6.15) with the decrease bound (6.15g), the applied ``u = v₀ + K(x − z₀)``, the
    candidate (6.14) and the fallbacks of
    :class:`~balustrade.control.multiobjective.MultiobjectivePCBFController`.
    ``problems`` holds ``"slack"`` (5.15) and ``"problem"`` (6.15) (parameters ``x0``,
    ``u_p``, ``bound``; the variables of (5.15))."""

    #: ``ρ`` of (6.15g) and the margin ``bound_tol · max(1, |bound|)`` added to the bound
    rho: float
    bound_tol: float
    #: an extra (5.15) solve per step for ``h_r`` (not emitted)
    record_h_r: bool
    #: the slack norm of ``h̃`` (ℓ1 in Algorithm 6.4)
    slack_norm: int | float = 1
    #: the recovery target whose attempt leads the first (5.15) and (6.15) solves
    #: (:mod:`balustrade.backends.recovery`; ``None``: none)
    recovery_target: object = None
    #: ordinary steps start (6.15) from the candidate (6.14) with the previous (6.15)'s
    #: multipliers (``False``: from the previous (6.15))
    candidate_duals: bool = False
    #: a failed ordinary (6.15) is tried once more from the candidate (6.14) with the
    #: previous (6.15)'s multipliers, before the cold retries
    candidate_second: bool = False


@dataclass(frozen=True)
class RAPSFDeployment(ProblemsDeployment):
    """Algorithm 4.1 (Chapter 4, SPEC §2.21): ``problems["main"]`` is (4.5) with the
    horizon ``N`` and the vertex data as parameters (``x0``, ``u_p``, ``theta``
    ``q × n_theta``, ``s``; variable ``v``), the applied ``u = K x + v*_0``, the stored
    plan, the backup ``K x``. The estimator and ``s`` stay in Python (``host``)."""

    #: the tube gain ``K`` (also the backup policy's)
    K: np.ndarray = field(repr=False)
    #: horizon and the number of vertex columns compiled into (4.5)
    N: int
    n_vertices: int
    #: Remark 4.6 (a shrunk-horizon solve before the stored plan): then ``problems`` also
    #: holds (4.5) with the horizon ``h`` as ``"shrunk<h>"`` for ``h = 1 … N−1``
    shrinking: bool
    #: the backup policy is the default ``K x``; otherwise the emitter takes the host's
    #: ``backup_law`` (an affine law or a CasADi function; a Python callable is refused)
    default_backup: bool
    #: the Python controller whose estimator and ``s`` feed the C (never solves there)
    host: object = field(repr=False)


@dataclass(frozen=True)
class LyapunovDeployment(ProblemsDeployment):
    """Algorithm 6.3 (Section 6.3.2, linear design (6.10)): ``problems["init"]`` is (6.3)
    without (6.3h) (parameters ``x0``, ``u_p``; variables ``z``, ``v``), solved on the first
    step; ``problems["problem"]`` is (6.10) (parameters ``x0``, ``u_p``, ``bound``), solved
    every step warm-started from the switching rule (6.6)/(6.7) with ``bound`` the right side
    of (6.3h) plus ``bound_tol · max(1, |bound|)``; fallbacks of
    :class:`~balustrade.control.multiobjective.MultiobjectiveLyapunovController`."""

    #: the nominal model ``x⁺ = A x + B u`` (``w`` measured as ``x_{k+1} − A x_k − B u_k``)
    A: np.ndarray = field(repr=False)
    B: np.ndarray = field(repr=False)
    #: the feedback of ``ξ_c`` (6.11) and ``ξ_f`` (6.12), and the weights of ``V`` (6.2)
    K: np.ndarray = field(repr=False)
    Q: np.ndarray = field(repr=False)
    R: np.ndarray = field(repr=False)
    P: np.ndarray = field(repr=False)
    N: int
    #: ``X_f`` (the switching rule's membership test) and, as ``(H, h)`` rows, the sets of
    #: (6.3b–g): ``X ⊖ E_i``, ``U ⊖ K E_i`` (``i < N``) and ``X_f ⊖ E_N``
    Xf: Polytope
    Xs: tuple[Polytope, ...] = field(repr=False)
    Us: tuple[Polytope, ...] = field(repr=False)
    Xf_N: Polytope = field(repr=False)
    #: input set of the projected-proposal fallback (a box for C)
    U: Set
    rho: float
    bound_tol: float


__all__ = ["ApproximateDeployment", "GridDeployment", "LyapunovDeployment",
           "MultiobjectiveDeployment",
           "PCBFDeployment", "ProblemsDeployment", "RAPSFDeployment", "RobustDeployment",
           "TubeDeployment"]
