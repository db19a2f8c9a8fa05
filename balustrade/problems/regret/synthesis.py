"""Regret-optimal synthesis problems of Chapter 3, stated as structured SDPs (SPEC 2.10–2.17).

Each builder states one thesis SDP in the synthesis language (:mod:`balustrade.dsl.synthesis`):
the decision variable θ = the causal entries of Ψ = SΦ_u (:class:`.Parametrization`), the
regret written as ``δᵀYᵀYδ`` with Y affine in θ (:mod:`.operators`), a few scalars, and one
arrow LMI ``[[a, bᵀ, yᵀ], [b, D, Lᵀ], [y, L, I]] ⪰ 0`` with ``L = Y[:, cols]``
(:func:`~balustrade.dsl.synthesis_arrow.arrow_lmi`) — the Schur complement form of the thesis
LMI after the compression ΦᵀCΦ − 𝒪 = YᵀY. The problem is an ordinary
:class:`~balustrade.dsl.synthesis.SynthesisProblem` (``compile_synthesis`` solves it with the LMI
as one cone); how the LMI reaches a solver — banded coordinates, chordal split, one cone — is a
lowering choice (:mod:`balustrade.backends.synthesis_structured`), not part of the problem.
Solving, certifying and the re-solve outside banded coordinates are in
:mod:`balustrade.control.regret_synthesis`, which also exports the thesis-named functions
(``dynamic_regret`` …) that build and solve in one call.

==============================  ==============================================================
builder                         thesis problem
==============================  ==============================================================
``dynamic_regret_problem``      (3.19), known x₀ and energy bound ω
``adversarial_regret_problem``  (3.24), adversarial δ (spectral norm of ΦᵀCΦ − 𝒪)
``generalized_regret_problem``  (3.28), weight W_w (I: dynamic regret, 𝒪: competitive ratio)
``zero_x0_regret_problem``      (3.30), x₀ = 0, and its adversarial-x₀ variant
``pointwise_regret_problem``    (3.32), pointwise ellipsoidal bounds w_kᵀPw_k ≤ 1
``pointwise_dynamic_problem``   (3.34), the dual with the 2/π guarantee (3.36)
``h2_problem``, ``hinf_problem`` SH2 and SH∞ baselines of Section 3.8 (SPEC 2.17 [Default])
==============================  ==============================================================

All accept ``constraints=`` (:class:`StateInputConstraints`) imposed robustly by (3.41) for a
pointwise set ``P`` or, for energy bounds, conservatively per step (Remark 3.16). Each problem
carries its solver-independent certificate (:mod:`.verify`): the exact worst-case level of a
controller for the energy-bound and adversarial problems, a certified lower bound for the
pointwise ones (3.32)/(3.34).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from balustrade._checks import as_matrix, as_vector, check_psd
from balustrade.dsl.synthesis import (
    Expr,
    SynthesisProblem,
    as_expr,
    sum_squares,
    total,
    vstack,
)
from balustrade.dsl.synthesis_arrow import arrow_lmi
from balustrade.errors import BalustradeError, ShapeError, moved_names
from balustrade.problems.regret.lifting import lq_lift
from balustrade.problems.regret.operators import Operators
from balustrade.problems.regret.parametrization import Parametrization, normalize_halfspaces
from balustrade.problems.regret.verify import (
    adversarial_level,
    generalized_level_energy,
    hinf_level,
    pointwise_regret_lower_bound,
    worst_case_regret_energy,
    zero_x0_level,
)

#: Φ_u and the variable values of a solution → ("exact" | "lower_bound", value)
Certificate = Callable[[np.ndarray, dict[str, np.ndarray]], tuple[str, float]]


@dataclass(frozen=True)
class StateInputConstraints:
    """Polytopic constraints in the normalized form (3.40): H_x x ≤ 1, H_u u ≤ 1 at every step."""

    Hx: np.ndarray
    Hu: np.ndarray

    @classmethod
    def from_halfspaces(cls, Ax: object, bx: object, Au: object, bu: object
                        ) -> StateInputConstraints:
        return cls(normalize_halfspaces(Ax, bx, "state constraints"),
                   normalize_halfspaces(Au, bu, "input constraints"))

    def check(self, n: int, m: int) -> None:
        if self.Hx.ndim != 2 or self.Hx.shape[1] != n:
            raise ShapeError("constraints Hx", ("k", n), self.Hx.shape)
        if self.Hu.ndim != 2 or self.Hu.shape[1] != m:
            raise ShapeError("constraints Hu", ("k", m), self.Hu.shape)

    def violation(self, x: np.ndarray, u: np.ndarray) -> float:
        """Largest max(Hz − 1) along trajectories (T+1, n), (T+1, m); ≤ 0 means satisfied."""
        return float(max(np.max(x @ self.Hx.T - 1.0), np.max(u @ self.Hu.T - 1.0)))


# ----------------------------------------------------------------------------------------------
# input handling
# ----------------------------------------------------------------------------------------------
def _x0(ops: Operators, x0: object) -> np.ndarray:
    return as_vector(x0, "x0", ops.n)


def _omega(omega: object) -> float:
    val = float(omega)
    if not np.isfinite(val) or val <= 0:
        raise BalustradeError(f"omega: the energy bound must be positive and finite, got {omega!r}")
    return val


def _weight(ops: Operators, W: object) -> np.ndarray:
    """W_w of (3.11): "I", "O" (competitive ratio) or a positive definite (n+pT)-matrix."""
    if isinstance(W, str):
        if W == "I":
            return np.eye(ops.nd)
        if W == "O":
            # (3.11) needs W_w ≻ 0; 𝒪 is singular when some δ has zero non-causal cost (e.g. a
            # singular Q_k), and the levels (3.29)/(3.30) then divide by zero
            return check_psd(ops.O, "W='O' (the benchmark matrix 𝒪 of (3.6); the competitive "
                             "ratio needs 𝒪 ≻ 0, e.g. every Q_k ≻ 0)", strict=True)
        raise BalustradeError(f"W: expected 'I', 'O' or a matrix, got {W!r}")
    Wm = as_matrix(W, "W", (ops.nd, ops.nd))
    return check_psd(Wm, "W", strict=True)


def _pointwise_P(ops: Operators, P: object) -> np.ndarray:
    Pm = as_matrix(P, "P", (ops.p, ops.p))
    return check_psd(Pm, "P", strict=True)


def _inv_sqrt(P: np.ndarray) -> np.ndarray:
    lam, V = np.linalg.eigh(P)
    return (V / np.sqrt(lam)) @ V.T


# ----------------------------------------------------------------------------------------------
# the problem object and its builder
# ----------------------------------------------------------------------------------------------
@dataclass
class RegretProblem:
    """A regret synthesis: the SDP, the map θ → Φ_u, its level and how to certify a solution.

    ``level`` maps the variable values of a solution to the level the thesis reports (γ, μ,
    Σλ̄_i, the SH2 cost); ``multipliers`` names the S-procedure variables a result reports."""

    sdp: SynthesisProblem
    par: Parametrization
    level: Callable[[dict[str, np.ndarray]], float]
    certify: Certificate | None = None
    multipliers: tuple[str, ...] = ()

    @property
    def name(self) -> str:
        return self.sdp.name

    @property
    def ops(self) -> Operators:
        return self.par.ops


def _value(name: str) -> Callable[[dict[str, np.ndarray]], float]:
    return lambda v: float(np.sum(v[name]))


class _Statement:
    """Helpers that let each builder read like its SDP: θ, the arrow LMI, (3.41)."""

    def __init__(self, ops: Operators, name: str):
        self.ops = ops
        self.par = Parametrization(ops)
        self.sdp = SynthesisProblem(name)
        self.theta = self.sdp.vector("theta", self.par.n_theta)

    def arrow(self, on: str, D: Sequence[tuple[object, np.ndarray]], a: object | None = None,
              b: Sequence[tuple[object, np.ndarray]] = (), x0: np.ndarray | None = None,
              name: str = "regret LMI", lq: tuple[object, object | None] | None = None
              ) -> None:
        """[[a, bᵀ, yᵀ], [b, D, Lᵀ], [y, L, I]] ⪰ 0 with L = Y[:, cols] and y = Y[:, x₀]x₀;
        ``on`` = "w" (cols = the disturbances w) or "delta" (cols = all of δ = (x₀, w)).

        ``lq = (μ, a_rest)`` declares that the first D term, the first b term and μ's part of
        ``a`` are μ·δᵀ𝒪δ with δ = (αx₀, w) (W_w = 𝒪; ``a_rest`` = a without it): the lowering
        may then state it through the LQ definition of 𝒪 (:mod:`.lifting`, ``lmi="lifted"``)."""
        ops = self.ops
        cols = slice(ops.n, ops.nd) if on == "w" else slice(0, ops.nd)
        b_dense = 0 if b and np.any(b[0][1] != 0) else None
        b = [(beta, vec) for beta, vec in b if np.any(vec != 0)]
        y = None if x0 is None else self.par.Y_x0(x0)
        lift = None
        if lq is not None and on == "w":
            lift = lq_lift(ops, x0, lq[0], dense=0, b_dense=b_dense, a_rest=lq[1])
        self.sdp.lmi(name, arrow_lmi(self.theta, self.par.Y(cols), D, a=a, b=b, y=y,
                                     col_blocks=_p_blocks(ops, 1 if on == "w" else 0),
                                     block=ops.p, row_block=ops.m, lift=lift))

    def constrain(self, constraints: StateInputConstraints | None, x0: np.ndarray | None,
                  P: np.ndarray | None = None, omega: float | None = None) -> None:
        """(3.41) for the pointwise set {wᵀPw ≤ 1}; per-step energy ‖w_k‖² ≤ ω (Remark 3.16):
        [H_z]_iΦ⁰x₀ + Σ_j ‖[H_z]_i[[Φ^w]]_j P^{-1/2}‖ ≤ 1, one norm per (row, block) shared by
        parallel rows (:meth:`.Parametrization.robust_constraints`)."""
        if constraints is None:
            return
        constraints.check(self.ops.n, self.ops.m)
        if P is not None:
            Pmh = _inv_sqrt(P)
        elif omega is not None:
            Pmh = np.sqrt(omega) * np.eye(self.ops.p)
        else:
            raise BalustradeError(f"{self.sdp.name}: constraints need a disturbance set "
                                  "(P or omega)")
        rows = self.par.robust_constraints(constraints.Hx, constraints.Hu, x0, Pmh)
        lhs = as_expr(rows.fixed)
        if rows.pieces:
            norms = self.sdp.vector("norms (3.41)", rows.G.shape[1], nonneg=True)
            self.sdp.soc("norms (3.41)", vstack([m.of(self.theta) for m in rows.pieces]),
                         norms, axis=1)
            lhs = as_expr(rows.G) @ norms + lhs
        if rows.F is not None:
            lhs = lhs + as_expr(rows.F) @ self.theta + rows.g
        self.sdp.subject_to("constraints (3.41)", lhs <= 1)

    def minimize(self, objective: Expr, level: Callable[[dict[str, np.ndarray]], float],
                 certify: Certificate | None = None, multipliers: tuple[str, ...] = ()
                 ) -> RegretProblem:
        self.sdp.minimize(objective)
        return RegretProblem(self.sdp, self.par, level, certify, multipliers)


def _block_term(P: np.ndarray, sl: slice, d: int) -> np.ndarray:
    """The d×d matrix with P on the diagonal block ``sl`` (one S-procedure term of (3.32))."""
    out = np.zeros((d, d))
    out[sl, sl] = P
    return out


def _p_blocks(ops: Operators, start_block: int = 1) -> list[slice]:
    """Slices of the w-blocks relative to the start of w (or of δ when start_block = 0)."""
    off = ops.d_blocks[start_block].start
    return [slice(sl.start - off, sl.stop - off) for sl in ops.d_blocks[start_block:]]


def _opt_P(ops: Operators, P: object | None) -> np.ndarray | None:
    return None if P is None else _pointwise_P(ops, P)


def _opt_omega(omega: object | None) -> float | None:
    return None if omega is None else _omega(omega)


def _is_O(W: object) -> bool:
    """W_w = 𝒪 given by name: the weight term has the LQ form of :mod:`.lifting`."""
    return isinstance(W, str) and W == "O"


def _label(W: object) -> str:
    return W if isinstance(W, str) else "user"


# ----------------------------------------------------------------------------------------------
# (3.19) dynamic regret, known x0, energy bound
# ----------------------------------------------------------------------------------------------
def dynamic_regret_problem(ops: Operators, x0: object, omega: float, *,
                           constraints: StateInputConstraints | None = None,
                           constraint_P: object | None = None) -> RegretProblem:
    """Theorem 3.5, SDP (3.19): min γ s.t. the worst-case regret over ‖w‖² ≤ ω is ≤ γ, i.e.
    [[γ − λω, 0, (Y⁰x₀)ᵀ], [0, λI, Y^wᵀ], [Y⁰x₀, Y^w, I]] ⪰ 0, λ ≥ 0."""
    x0v, om = _x0(ops, x0), _omega(omega)
    st = _Statement(ops, "dynamic regret (3.19)")
    gamma, lam = st.sdp.scalar("gamma"), st.sdp.scalar("lambda", nonneg=True)
    st.arrow("w", D=[(lam, np.eye(ops.p * ops.T))], a=gamma - om * lam, x0=x0v)
    st.constrain(constraints, x0v, _opt_P(ops, constraint_P), om)
    return st.minimize(gamma, _value("gamma"), lambda Pu, v: (
        "exact", worst_case_regret_energy(ops, Pu, x0v, om).upper), ("lambda",))


# ----------------------------------------------------------------------------------------------
# (3.24) adversarial δ
# ----------------------------------------------------------------------------------------------
def adversarial_regret_problem(ops: Operators, *,
                               constraints: StateInputConstraints | None = None,
                               x0: object | None = None, constraint_P: object | None = None,
                               omega: float | None = None) -> RegretProblem:
    """(3.24): min ‖ΦᵀCΦ − 𝒪‖₂ = min γ s.t. γI − YᵀY ⪰ 0, i.e. [[γI, Yᵀ], [Y, I]] ⪰ 0
    (worst-case regret ωγ* on ‖δ‖² ≤ ω)."""
    st = _Statement(ops, "adversarial regret (3.24)")
    gamma = st.sdp.scalar("gamma")
    st.arrow("delta", D=[(gamma, np.eye(ops.nd))])
    st.constrain(constraints, None if x0 is None else _x0(ops, x0), _opt_P(ops, constraint_P),
                 _opt_omega(omega))
    return st.minimize(gamma, _value("gamma"),
                       lambda Pu, v: ("exact", adversarial_level(ops, Pu)))


# ----------------------------------------------------------------------------------------------
# (3.28) generalized regret
# ----------------------------------------------------------------------------------------------
def generalized_regret_problem(ops: Operators, x0: object, omega: float, W: object = "I", *,
                               constraints: StateInputConstraints | None = None,
                               constraint_P: object | None = None) -> RegretProblem:
    """Theorem 3.8, SDP (3.28): min μ s.t. J − J* ≤ μ δᵀW_wδ for all ‖w‖² ≤ ω, i.e.
    [[μx₀ᵀW₁x₀ − λω, μ(W₂x₀)ᵀ, (Y⁰x₀)ᵀ], [μW₂x₀, λI + μW₃, Y^wᵀ], [Y⁰x₀, Y^w, I]] ⪰ 0.

    W = "I" gives dynamic regret over the whole δ (as in the authors' code), W = "O" the
    competitive ratio J ≤ (1 + μ)J*.
    """
    x0v, om = _x0(ops, x0), _omega(omega)
    Wm = _weight(ops, W)
    W1, W2, W3 = ops.partition(Wm)
    st = _Statement(ops, f"generalized regret (3.28), W={_label(W)}")
    mu, lam = st.sdp.scalar("mu"), st.sdp.scalar("lambda", nonneg=True)
    st.arrow("w", D=[(mu, W3), (lam, np.eye(W3.shape[0]))],
             a=float(x0v @ W1 @ x0v) * mu - om * lam, b=[(mu, W2 @ x0v)], x0=x0v,
             lq=(mu, -om * lam) if _is_O(W) else None)
    st.constrain(constraints, x0v, _opt_P(ops, constraint_P), om)
    return st.minimize(mu, _value("mu"), lambda Pu, v: ("exact", generalized_level_energy(
        ops, Pu, x0v, om, Wm, guess=float(v["mu"]))), ("lambda",))


# ----------------------------------------------------------------------------------------------
# (3.30) x0 = 0 and adversarial x0
# ----------------------------------------------------------------------------------------------
def zero_x0_regret_problem(ops: Operators, W: object = "I", *, adversarial_x0: bool = False,
                           constraints: StateInputConstraints | None = None,
                           constraint_P: object | None = None, omega: float | None = None
                           ) -> RegretProblem:
    """(3.30): min μ s.t. μW₃ − Φ^wᵀCΦ^w + 𝒪₃ ⪰ 0, i.e. [[μW₃, Y^wᵀ], [Y^w, I]] ⪰ 0
    (x₀ = 0; no ω needed). The tight level (3.29).

    ``adversarial_x0=True``: the same on the whole δ with W_w and 𝒪 (SPEC 2.13).
    """
    Wm = _weight(ops, W)
    name = "adversarial-x0 regret (3.30)" if adversarial_x0 else "zero-x0 regret (3.30)"
    st = _Statement(ops, name)
    mu = st.sdp.scalar("mu")
    if adversarial_x0:
        st.arrow("delta", D=[(mu, Wm)])
    else:
        st.arrow("w", D=[(mu, ops.partition(Wm)[2])], lq=(mu, None) if _is_O(W) else None)
    st.constrain(constraints, None if adversarial_x0 else np.zeros(ops.n),
                 _opt_P(ops, constraint_P), _opt_omega(omega))
    return st.minimize(mu, _value("mu"),
                       lambda Pu, v: ("exact", zero_x0_level(ops, Pu, Wm, adversarial_x0)))


# ----------------------------------------------------------------------------------------------
# (3.32) pointwise ellipsoidal bounds, generalized; (3.34) pointwise dynamic regret
# ----------------------------------------------------------------------------------------------
def pointwise_regret_problem(ops: Operators, x0: object, P: object, W: object = "I", *,
                             constraints: StateInputConstraints | None = None) -> RegretProblem:
    """SDP (3.32): min μ̄ s.t. J − J* ≤ μ̄ δᵀW_wδ for all w_kᵀPw_k ≤ 1 (S-procedure, λ̄_i ≥ 0):
    [[μ̄x₀ᵀW₁x₀ − Σλ̄_i, μ̄(W₂x₀)ᵀ, (Y⁰x₀)ᵀ], [μ̄W₂x₀, μ̄W₃ + Σλ̄_iP_i, Y^wᵀ], [Y⁰x₀, Y^w, I]] ⪰ 0
    with P_i = P on the block of w_{i−1}."""
    x0v, Pm = _x0(ops, x0), _pointwise_P(ops, P)
    Wm = _weight(ops, W)
    W1, W2, W3 = ops.partition(Wm)
    st = _Statement(ops, f"pointwise regret (3.32), W={_label(W)}")
    mu, lams = st.sdp.scalar("mu"), st.sdp.vector("lambda", ops.T, nonneg=True)
    d = W3.shape[0]
    S_terms = [(lams[i], _block_term(Pm, sl, d)) for i, sl in enumerate(_p_blocks(ops))]
    st.arrow("w", D=[(mu, W3), *S_terms], a=float(x0v @ W1 @ x0v) * mu - total(lams),
             b=[(mu, W2 @ x0v)], x0=x0v, lq=(mu, -total(lams)) if _is_O(W) else None)
    st.constrain(constraints, x0v, Pm)
    return st.minimize(mu, _value("mu"), lambda Pu, v: (
        "lower_bound", _pointwise_lb(ops, Pu, x0v, Pm, Wm)), ("lambda",))


def pointwise_dynamic_problem(ops: Operators, x0: object, P: object, *,
                              constraints: StateInputConstraints | None = None
                              ) -> RegretProblem:
    """Theorem 3.12, SDP (3.34): γ̄* = min Σ_{i=0}^T λ̄_i, with (2/π)γ̄* ≤ R⁰_PWB ≤ γ̄* (3.36):
    [[λ̄_0, 0, (Y⁰x₀)ᵀ], [0, Σ_{i≥1} λ̄_iP_i, Y^wᵀ], [Y⁰x₀, Y^w, I]] ⪰ 0."""
    x0v, Pm = _x0(ops, x0), _pointwise_P(ops, P)
    st = _Statement(ops, "pointwise dynamic regret (3.34)")
    lams = st.sdp.vector("lambda", ops.T + 1, nonneg=True)
    d = ops.p * ops.T
    st.arrow("w", D=[(lams[i + 1], _block_term(Pm, sl, d)) for i, sl in enumerate(_p_blocks(ops))],
             a=lams[0], x0=x0v)
    st.constrain(constraints, x0v, Pm)
    return st.minimize(total(lams), _value("lambda"), lambda Pu, v: (
        "lower_bound", _pointwise_lb(ops, Pu, x0v, Pm, None)), ("lambda",))


def _pointwise_lb(ops: Operators, Phi_u: np.ndarray, x0: np.ndarray, P: np.ndarray,
                  W: np.ndarray | None) -> float:
    """Certified lower bound on the pointwise worst case of Φ_u (verify.py; 20 starts)."""
    return pointwise_regret_lower_bound(ops, Phi_u, x0, P, W=W, starts=20, iters=200).value


# ----------------------------------------------------------------------------------------------
# baselines of Section 3.8 (SPEC 2.17 [Default])
# ----------------------------------------------------------------------------------------------
def h2_problem(ops: Operators, x0: object, *, constraints: StateInputConstraints | None = None,
               constraint_P: object | None = None, omega: float | None = None
               ) -> RegretProblem:
    """SH2: min ‖C^{1/2}Φ⁰x₀‖² + ‖C^{1/2}Φ^w‖_F² (expected cost for white w with unit covariance).

    Written as ‖Y⁰x₀‖² + ‖Y^w‖_F² + x₀ᵀ𝒪₁x₀ + tr 𝒪₃; the level reported is that expected cost.
    """
    x0v = _x0(ops, x0)
    st = _Statement(ops, "SH2")
    O1, _, O3 = ops.O_parts
    const = float(x0v @ O1 @ x0v + np.trace(O3))
    y0, Yw = st.par.Y_x0(x0v), st.par.Y(slice(ops.n, ops.nd))
    st.constrain(constraints, x0v, _opt_P(ops, constraint_P), _opt_omega(omega))

    def level(v: dict[str, np.ndarray]) -> float:
        return float(np.sum(y0.value(v["theta"]) ** 2) + np.sum(Yw.value(v["theta"]) ** 2)
                     + const)

    return st.minimize(sum_squares(y0.flat(st.theta)) + sum_squares(Yw.flat(st.theta)), level)


def hinf_problem(ops: Operators, *, x0: object | None = None,
                 constraints: StateInputConstraints | None = None,
                 constraint_P: object | None = None, omega: float | None = None
                 ) -> RegretProblem:
    """SH∞: min γ s.t. γI − ΦᵀCΦ ⪰ 0 on the whole δ (SLP H∞); here γI − 𝒪 − YᵀY ⪰ 0, i.e.
    [[γI − 𝒪, Yᵀ], [Y, I]] ⪰ 0."""
    st = _Statement(ops, "SH-inf")
    gamma = st.sdp.scalar("gamma")
    st.arrow("delta", D=[(gamma, np.eye(ops.nd)), (-1.0, ops.O)])
    st.constrain(constraints, None if x0 is None else _x0(ops, x0), _opt_P(ops, constraint_P),
                 _opt_omega(omega))
    return st.minimize(gamma, _value("gamma"), lambda Pu, v: ("exact", hinf_level(ops, Pu)))

#: the solve-and-certify functions that moved out of problems/regret (issue #13), for the
#: deprecated aliases of this module and of the package (problems/regret/__init__.py)
MOVED_SOLVERS: dict[str, str] = {name: "balustrade.control.regret_synthesis" for name in (
    "SynthesisResult", "adversarial_regret", "dynamic_regret", "generalized_regret", "h2",
    "hinf", "pointwise_dynamic_regret", "pointwise_regret", "zero_x0_regret")}

__getattr__ = moved_names(__name__, MOVED_SOLVERS)
