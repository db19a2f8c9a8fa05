"""Regret-optimal synthesis problems of Chapter 3 on the cvxpy backend (SPEC 2.10–2.17).

Each function builds one SDP over the causal entries of Φ_u (:class:`.Parametrization`), with
the regret written as ``δᵀYᵀYδ`` (:mod:`.operators`) and the LMIs split along their chordal
structure (:mod:`.lmi`), solves it (Clarabel by default) and returns a
:class:`SynthesisResult`. Infeasible or failed solves return a status, never raise.

==========================  =============================================================
function                    thesis problem
==========================  =============================================================
``dynamic_regret``          (3.19), known x₀ and energy bound ω
``adversarial_regret``      (3.24), adversarial δ (spectral norm of ΦᵀCΦ − 𝒪)
``generalized_regret``      (3.28), weight W_w (I: dynamic regret, 𝒪: competitive ratio)
``zero_x0_regret``          (3.30), x₀ = 0, and its adversarial-x₀ variant
``pointwise_regret``        (3.32), pointwise ellipsoidal bounds w_kᵀPw_k ≤ 1
``pointwise_dynamic_regret`` (3.34), the dual with the 2/π guarantee (3.36)
``h2``, ``hinf``            SH2 and SH∞ baselines of Section 3.8 (SPEC 2.17 [Default])
==========================  =============================================================

All accept ``constraints=`` (:class:`StateInputConstraints`) imposed robustly by (3.41) for a
pointwise set ``P`` or, for energy bounds, conservatively per step (Remark 3.16).

Every result carries a solver-independent certificate (:mod:`.verify`) in
``info["certificate"]``: for the energy-bound and adversarial problems the exact worst-case
level of the returned controller, which is then the reported ``level`` (the SDP's own value is
``info["sdp_level"]``; the two agree to the solver's accuracy when the solve is accurate, and a
level is never reported below what its controller attains); for the pointwise problems
(3.32)/(3.34) a certified lower bound on the controller's worst case, which must not exceed the
level. ``res.ok`` means: the solver reports ``optimal`` (full accuracy) and the certificate
agrees. ``optimal_inaccurate`` is never ``ok`` — Clarabel's reduced tolerances were measured
to hide a level 33 % above the optimum in banded coordinates (:mod:`.banded`), and an
"optimal" banded SCRW level 1.5e-5 below what its controller attains — so a banded solve that
is not ok is re-solved outside banded coordinates, the reason
recorded in ``info["banded_fallback"]`` (or, when that form cannot run, in
``info["banded_retry"]`` and the inaccurate result is returned with ``ok`` False).
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import cvxpy as cp
import numpy as np

from balustrade._checks import as_matrix, as_vector, check_psd
from balustrade.errors import BalustradeError, ShapeError
from balustrade.problems.regret.banded import NotBanded
from balustrade.problems.regret.lmi import Leaf, arrow_lmi, banded_lmi, diagonal_groups
from balustrade.problems.regret.operators import Operators, controller_from_responses
from balustrade.problems.regret.parametrization import Parametrization, normalize_halfspaces
from balustrade.problems.regret.verify import (
    adversarial_level,
    generalized_level_energy,
    hinf_level,
    pointwise_regret_lower_bound,
    worst_case_regret_energy,
    zero_x0_level,
)

OK_STATUSES = ("optimal", "optimal_inaccurate")
# How the LMI reaches the solver: "banded" (banded coordinates, one cone the solver decomposes;
# falls back to "split" when the structure is missing), "split" (chordal split of lmi.py),
# "single" (one compressed cone).
LMI_FORMS = ("banded", "split", "single")


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


@dataclass
class SynthesisResult:
    """Outcome of one synthesis: status, optimal level, responses Φ and controller K (3.15)."""

    name: str
    status: str
    level: float | None
    ops: Operators = field(repr=False)
    Phi_x: np.ndarray | None = field(default=None, repr=False)
    Phi_u: np.ndarray | None = field(default=None, repr=False)
    K: np.ndarray | None = field(default=None, repr=False)
    solve_time: float = 0.0
    total_time: float = 0.0
    multipliers: dict = field(default_factory=dict, repr=False)
    info: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        """Solved to full accuracy (status "optimal") and the level agrees with its certificate.

        "optimal_inaccurate" is not ok: the solver met only its reduced tolerances, and on
        ill-conditioned SDPs (banded coordinates with the 𝒪 weight) that was measured to mean a
        level far from the optimum. Such a result keeps its controller and certificate for a
        caller that checks them itself (``controller(allow_inaccurate=True)``).
        """
        return (self.status == "optimal" and self.K is not None
                and self.info.get("certificate", {}).get("consistent", True))

    def gain(self, allow_inaccurate: bool = False) -> np.ndarray:
        """The causal gain K of (3.15) if usable (see :attr:`ok`); run it in closed loop with
        :meth:`balustrade.control.regret.RegretController.from_result`."""
        usable = self.ok or (allow_inaccurate and self.status in OK_STATUSES
                             and self.K is not None)
        if not usable:
            raise BalustradeError(f"{self.name}: no controller, synthesis status {self.status!r}"
                                  + ("" if self.K is None else " (not certified, see .ok)"))
        return self.K


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
            return ops.O
        raise BalustradeError(f"W: expected 'I', 'O' or a matrix, got {W!r}")
    Wm = as_matrix(W, "W", (ops.nd, ops.nd))
    return check_psd(Wm, "W", strict=True)


def _pointwise_P(ops: Operators, P: object) -> np.ndarray:
    Pm = as_matrix(P, "P", (ops.p, ops.p))
    return check_psd(Pm, "P", strict=True)


def _inv_sqrt(P: np.ndarray) -> np.ndarray:
    lam, V = np.linalg.eigh(P)
    return (V / np.sqrt(lam)) @ V.T


def _is_block_diag(W: np.ndarray, ops: Operators, tol: float = 1e-12) -> bool:
    mask = np.ones_like(W, dtype=bool)
    for sl in ops.d_blocks:
        mask[sl, sl] = False
    return bool(np.max(np.abs(W[mask]), initial=0.0) <= tol * max(1.0, np.max(np.abs(W))))


# ----------------------------------------------------------------------------------------------
# the common solve path
# ----------------------------------------------------------------------------------------------
class _Problem:
    """Collects constraints over one :class:`Parametrization`, solves, packs the result."""

    def __init__(self, ops: Operators, name: str, lmi: str):
        self.t0 = time.perf_counter()
        if lmi not in LMI_FORMS:
            raise BalustradeError(f"lmi: expected one of {LMI_FORMS}, got {lmi!r}")
        self.ops, self.name, self.lmi = ops, name, lmi
        self.form = "single" if lmi == "single" else "split"   # until try_banded succeeds
        self.fallback_reason: str | None = None
        self.par = Parametrization(ops)
        self.cons: list[cp.Constraint] = []
        self.extra: dict[str, cp.Expression] = {}

    @property
    def split(self) -> bool:
        """Whether the fallback (non-banded) LMI is the chordal split rather than one cone."""
        return self.lmi != "single"

    def try_banded(self, cols: slice, D_terms: list, a: cp.Expression | None = None,
                   b_terms: list | None = None, y: cp.Expression | None = None) -> bool:
        """Add the LMI in banded coordinates (:mod:`.banded`); False if not asked/possible."""
        if self.lmi != "banded":
            return False
        out = banded_lmi(self.par, cols, D_terms, a=a, b_terms=b_terms or [], y=y)
        if isinstance(out, NotBanded):
            self.fallback_reason = out.reason
            return False
        self.cons += out
        self.form = "banded"
        return True

    def add_constraints(self, constraints: StateInputConstraints | None, x0: np.ndarray | None,
                        P: np.ndarray | None = None, omega: float | None = None) -> None:
        """(3.41) for the pointwise set {wᵀPw ≤ 1}; per-step energy ‖w_k‖² ≤ ω (Remark 3.16)."""
        if constraints is None:
            return
        constraints.check(self.ops.n, self.ops.m)
        if P is not None:
            Pmh = _inv_sqrt(P)
        elif omega is not None:
            Pmh = np.sqrt(omega) * np.eye(self.ops.p)
        else:
            raise BalustradeError(f"{self.name}: constraints need a disturbance set (P or omega)")
        self.cons += self.par.robust_constraints(constraints.Hx, constraints.Hu, x0, Pmh)

    def solve(self, objective: cp.Expression, level_fn, solver: str, solver_opts: dict,
              minimize: bool = True, certify: Callable[[np.ndarray], tuple[str, float]] | None
              = None) -> SynthesisResult:
        """Solve; with ``certify`` (Φ_u → ("exact" | "lower_bound", value)) attach the
        solver-independent certificate of :mod:`.verify` (module docstring)."""
        ops = self.ops
        prob = cp.Problem(cp.Minimize(objective) if minimize else cp.Maximize(objective),
                          self.cons)
        try:
            prob.solve(solver=solver, **_defaults(solver, self.form == "split", dict(solver_opts)))
            status = str(prob.status)
        except cp.error.SolverError as exc:
            status = f"solver_error: {exc}"
        total = time.perf_counter() - self.t0
        stats = getattr(prob, "solver_stats", None)
        solve_time = float(stats.solve_time) if stats is not None and stats.solve_time else total
        res = SynthesisResult(self.name, status, None, ops, solve_time=solve_time,
                              total_time=total,
                              info={"n_theta": self.par.theta.size,
                                    "psd_cone_sizes": _psd_sizes(prob), "lmi": self.form,
                                    "banded_fallback": self.fallback_reason})
        if status in OK_STATUSES and self.par.theta.value is not None:
            Phi_u = self.par.phi_u_value()
            Phi_x = ops.phi_x(Phi_u)
            res.Phi_u, res.Phi_x = Phi_u, Phi_x
            res.K = controller_from_responses(ops, Phi_x, Phi_u)
            res.level = float(level_fn())
            res.multipliers = {k: np.asarray(v.value).copy() for k, v in self.extra.items()
                               if v.value is not None}
            if certify is not None:
                _attach_certificate(res, *certify(Phi_u))
            res.total_time = time.perf_counter() - self.t0
        return res


# Relative slack of the certificate checks: the solver's tolerances (1e-8) with margin.
CERT_RTOL = 1e-6


def _attach_certificate(res: SynthesisResult, kind: str, value: float) -> None:
    """The SDP's level must bound what its own controller attains: consistent when the exact
    level ("exact") or the certified lower bound ("lower_bound") does not exceed it beyond
    CERT_RTOL. An exact level becomes the reported level (the SDP value stays in
    info["sdp_level"]): it is what the returned controller guarantees."""
    sdp = float(res.level)
    cert = {"kind": kind, "value": float(value), "sdp_level": sdp,
            "consistent": bool(value <= sdp + CERT_RTOL * max(abs(sdp), 1e-12))}
    if kind == "exact":
        res.level = float(value)
    res.info["certificate"] = cert
    res.info["sdp_level"] = sdp


def _retry_outside_banded(fn: Callable[..., SynthesisResult]) -> Callable[..., SynthesisResult]:
    """A banded solve that is not ok (not "optimal", or its level below what its own controller
    attains: both measured with the 𝒪 weight, banded.py) is re-solved in the form used when banded
    coordinates do not apply (``lmi="split"``: the chordal split, or one dense cone where no
    split exists, refused with "too_large" when it would not fit in memory). The retry is
    returned when it is ok, with the banded attempt in info["banded_fallback"]; otherwise the
    banded result is returned with the retry's outcome in info["banded_retry"]."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs) -> SynthesisResult:
        res = fn(*args, **kwargs)
        if res.info.get("lmi") != "banded" or res.ok:
            return res
        retry = fn(*args, **{**kwargs, "lmi": "split"})
        cert = res.info.get("certificate", {})
        why = (f"certificate {cert.get('kind')} {cert.get('value')} above the SDP level "
               f"{cert.get('sdp_level')}" if not cert.get("consistent", True) else "")
        attempt = (f"banded solve ended {res.status!r} (level {res.level}"
                   + (f"; {why}" if why else "") + f", {res.total_time:.1f} s); "
                   "re-solved with lmi='split'")
        if retry.ok:
            retry.info["banded_fallback"] = attempt
            retry.total_time += res.total_time
            return retry
        res.info["banded_retry"] = {"status": retry.status, "level": retry.level,
                                    "message": retry.info.get("message")}
        res.total_time += retry.total_time
        return res

    return wrapper


# Clarabel keeps a dense block of (svec size)² per PSD cone in its KKT system; the measured
# peak resident memory was ≈ 7 such blocks (22.8 GB for the 203-cone of SCRW at T = 25).
_CLARABEL_DENSE_CONE_FACTOR = 7 * 8


def _mem_available_bytes() -> float:
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable"):
                    return int(line.split()[1]) * 1024.0
    except OSError:
        pass
    return float("inf")


def _dense_cone_refusal(pr: _Problem, size: int, solver: str) -> SynthesisResult | None:
    """A status instead of an out-of-memory kill: a dense PSD cone too large for Clarabel."""
    if solver.upper() != "CLARABEL":
        return None
    svec = size * (size + 1) // 2
    need = _CLARABEL_DENSE_CONE_FACTOR * float(svec) ** 2
    avail = _mem_available_bytes()
    if need <= 0.8 * avail:
        return None
    msg = (f"{pr.name}: one dense PSD cone of size {size} needs about {need / 2**30:.1f} GB "
           f"with Clarabel, {avail / 2**30:.1f} GB available; use solver='SCS' (it only "
           "needs eigendecompositions of the cone)")
    return SynthesisResult(pr.name, "too_large", None, pr.ops,
                           total_time=time.perf_counter() - pr.t0,
                           info={"message": msg, "psd_cone_sizes": [size]})


def _psd_sizes(prob: cp.Problem) -> list[int]:
    return sorted({int(c.args[0].shape[0]) for c in prob.constraints
                   if isinstance(c, cp.constraints.PSD)}, reverse=True)


def _solver_opts(solver_opts: dict | None) -> dict:
    return dict(solver_opts or {})


def _defaults(solver: str, split: bool, opts: dict) -> dict:
    """Clarabel: our split is already the chordal decomposition; its own merging of the
    cones only enlarges them again (measured 2.5x slower), so it is switched off."""
    if solver.upper() == "CLARABEL" and split:
        opts.setdefault("chordal_decomposition_enable", False)
    return opts


def _block_term(P: np.ndarray, sl: slice, d: int) -> np.ndarray:
    """The d×d matrix with P on the diagonal block ``sl`` (one S-procedure term of (3.32))."""
    out = np.zeros((d, d))
    out[sl, sl] = P
    return out


def _p_blocks(ops: Operators, start_block: int = 1) -> list[slice]:
    """Slices of the w-blocks relative to the start of w (or of δ when start_block = 0)."""
    off = ops.d_blocks[start_block].start
    return [slice(sl.start - off, sl.stop - off) for sl in ops.d_blocks[start_block:]]


# ----------------------------------------------------------------------------------------------
# (3.19) dynamic regret, known x0, energy bound
# ----------------------------------------------------------------------------------------------
@_retry_outside_banded
def dynamic_regret(ops: Operators, x0: object, omega: float, *,
                   constraints: StateInputConstraints | None = None,
                   constraint_P: object | None = None, lmi: str = "banded",
                   solver: str = "CLARABEL", solver_opts: dict | None = None) -> SynthesisResult:
    """Theorem 3.5, SDP (3.19): min γ s.t. the worst-case regret over ‖w‖² ≤ ω is ≤ γ."""
    x0v, om = _x0(ops, x0), _omega(omega)
    pr = _Problem(ops, "dynamic regret (3.19)", lmi)
    gamma, lam = cp.Variable(), cp.Variable(nonneg=True)
    w_cols = slice(ops.n, ops.nd)
    a, y = gamma - lam * om, pr.par.Y_x0(x0v)
    if not pr.try_banded(w_cols, [(lam, np.eye(ops.p * ops.T))], a=a, y=y):
        Yw = pr.par.Y(w_cols)
        leaves = [Leaf(lam * np.eye(ops.p), Yw[:, sl]) for sl in _p_blocks(ops)]
        pr.cons += arrow_lmi(pr.par.M, leaves, a=a, y=y, split=pr.split)
    pr.add_constraints(constraints, x0v, _opt_P(ops, constraint_P), om)
    pr.extra = {"lambda": lam}
    return pr.solve(gamma, lambda: gamma.value, solver, _solver_opts(solver_opts),
                    certify=lambda Pu: ("exact", worst_case_regret_energy(ops, Pu, x0v, om).upper))


def _opt_P(ops: Operators, P: object | None) -> np.ndarray | None:
    return None if P is None else _pointwise_P(ops, P)


# ----------------------------------------------------------------------------------------------
# (3.24) adversarial δ
# ----------------------------------------------------------------------------------------------
@_retry_outside_banded
def adversarial_regret(ops: Operators, *, constraints: StateInputConstraints | None = None,
                       x0: object | None = None, constraint_P: object | None = None,
                       omega: float | None = None, lmi: str = "banded",
                       solver: str = "CLARABEL", solver_opts: dict | None = None
                       ) -> SynthesisResult:
    """(3.24): min ‖ΦᵀCΦ − 𝒪‖₂ = min γ s.t. γI − YᵀY ⪰ 0 (worst-case regret ωγ* on ‖δ‖² ≤ ω)."""
    pr = _Problem(ops, "adversarial regret (3.24)", lmi)
    gamma = cp.Variable()
    all_cols = slice(0, ops.nd)
    if not pr.try_banded(all_cols, [(gamma, np.eye(ops.nd))]):
        Y = pr.par.Y(all_cols)
        leaves = [Leaf(gamma * np.eye(sl.stop - sl.start), Y[:, sl]) for sl in ops.d_blocks]
        pr.cons += arrow_lmi(pr.par.M, leaves, split=pr.split)
    x0v = None if x0 is None else _x0(ops, x0)
    pr.add_constraints(constraints, x0v, _opt_P(ops, constraint_P),
                       None if omega is None else _omega(omega))
    return pr.solve(gamma, lambda: gamma.value, solver, _solver_opts(solver_opts),
                    certify=lambda Pu: ("exact", adversarial_level(ops, Pu)))


# ----------------------------------------------------------------------------------------------
# (3.28) generalized regret
# ----------------------------------------------------------------------------------------------
@_retry_outside_banded
def generalized_regret(ops: Operators, x0: object, omega: float, W: object = "I", *,
                       constraints: StateInputConstraints | None = None,
                       constraint_P: object | None = None, lmi: str = "banded",
                       solver: str = "CLARABEL", solver_opts: dict | None = None
                       ) -> SynthesisResult:
    """Theorem 3.8, SDP (3.28): min μ s.t. J − J* ≤ μ δᵀW_wδ for all ‖w‖² ≤ ω.

    W = "I" gives dynamic regret over the whole δ (as in the authors' code), W = "O" the
    competitive ratio J ≤ (1 + μ)J*.
    """
    x0v, om = _x0(ops, x0), _omega(omega)
    Wm = _weight(ops, W)
    W1, W2, W3 = ops.partition(Wm)
    pr = _Problem(ops, f"generalized regret (3.28), W={W if isinstance(W, str) else 'user'}",
                  lmi)
    mu, lam = cp.Variable(), cp.Variable(nonneg=True)
    a = mu * float(x0v @ W1 @ x0v) - lam * om
    b_full = W2 @ x0v
    pr.cons += _energy_lmi(pr, mu, lam, W3, b_full, a, x0v)
    pr.add_constraints(constraints, x0v, _opt_P(ops, constraint_P), om)
    pr.extra = {"lambda": lam}
    return pr.solve(mu, lambda: mu.value, solver, _solver_opts(solver_opts),
                    certify=lambda Pu: ("exact", generalized_level_energy(ops, Pu, x0v, om, Wm,
                                                                      guess=mu.value)))


def _energy_lmi(pr: _Problem, mu: cp.Variable, lam: cp.Variable | None, W3: np.ndarray,
                b_full: np.ndarray, a: cp.Expression | None, x0v: np.ndarray | None
                ) -> list[cp.Constraint]:
    """Arrow LMI with D = λI + μW₃ on the w-block: banded coordinates if possible, else the
    chordal split (after rotating w by the eigenvectors of W₃ if it is dense)."""
    ops, M = pr.ops, pr.par.M
    w_cols = slice(ops.n, ops.nd)
    has_b = bool(np.any(b_full != 0))
    lam_I = 0 if lam is None else lam
    y = None if x0v is None else pr.par.Y_x0(x0v)
    D_terms = [(mu, W3)] + ([] if lam is None else [(lam, np.eye(W3.shape[0]))])
    if pr.try_banded(w_cols, D_terms, a=a, b_terms=[(mu, b_full)] if has_b else [], y=y):
        return []
    if _is_block_diag(np.pad(W3, ((ops.n, 0), (ops.n, 0))), ops):
        Yw = pr.par.Y(w_cols)
        leaves = [Leaf(lam_I * np.eye(sl.stop - sl.start) + mu * W3[sl, sl], Yw[:, sl],
                       (mu * b_full[sl]) if has_b else None) for sl in _p_blocks(ops)]
    else:
        evals, U = np.linalg.eigh(W3)
        YwU = pr.par.Y_times(w_cols, U)
        diag = lam_I * np.ones(evals.size) + mu * evals
        bU = U.T @ b_full
        leaves = [Leaf(D, YwU[:, sl], (mu * bU[sl]) if has_b else None)
                  for sl, D in diagonal_groups(diag, ops.p)]
    return arrow_lmi(M, leaves, a=a, y=y, split=pr.split)


# ----------------------------------------------------------------------------------------------
# (3.30) x0 = 0 and adversarial x0
# ----------------------------------------------------------------------------------------------
@_retry_outside_banded
def zero_x0_regret(ops: Operators, W: object = "I", *, adversarial_x0: bool = False,
                   constraints: StateInputConstraints | None = None,
                   constraint_P: object | None = None, omega: float | None = None,
                   lmi: str = "banded", solver: str = "CLARABEL",
                   solver_opts: dict | None = None) -> SynthesisResult:
    """(3.30): min μ s.t. μW₃ − Φ^wᵀCΦ^w + 𝒪₃ ⪰ 0 (x₀ = 0; no ω needed). The tight level (3.29).

    ``adversarial_x0=True``: the same on the whole δ with W_w and 𝒪 (SPEC 2.13).
    """
    Wm = _weight(ops, W)
    name = "adversarial-x0 regret (3.30)" if adversarial_x0 else "zero-x0 regret (3.30)"
    pr = _Problem(ops, name, lmi)
    mu = cp.Variable()
    if adversarial_x0:
        if not pr.try_banded(slice(0, ops.nd), [(mu, Wm)]):
            evals, U = np.linalg.eigh(Wm)
            YU = pr.par.Y_times(slice(0, ops.nd), U)
            leaves = [Leaf(D, YU[:, sl]) for sl, D in diagonal_groups(mu * evals, ops.p)]
            pr.cons += arrow_lmi(pr.par.M, leaves, split=pr.split)
    else:
        W3 = ops.partition(Wm)[2]
        pr.cons += _energy_lmi(pr, mu, None, W3, np.zeros(ops.p * ops.T), None, None)
    x0v = np.zeros(ops.n)
    pr.add_constraints(constraints, None if adversarial_x0 else x0v,
                       _opt_P(ops, constraint_P), None if omega is None else _omega(omega))
    return pr.solve(mu, lambda: mu.value, solver, _solver_opts(solver_opts),
                    certify=lambda Pu: ("exact", zero_x0_level(ops, Pu, Wm, adversarial_x0)))


# ----------------------------------------------------------------------------------------------
# (3.32) pointwise ellipsoidal bounds, generalized; (3.34) pointwise dynamic regret
# ----------------------------------------------------------------------------------------------
@_retry_outside_banded
def pointwise_regret(ops: Operators, x0: object, P: object, W: object = "I", *,
                     constraints: StateInputConstraints | None = None, lmi: str = "banded",
                     solver: str = "CLARABEL", solver_opts: dict | None = None
                     ) -> SynthesisResult:
    """SDP (3.32): min μ̄ s.t. J − J* ≤ μ̄ δᵀW_wδ for all w_kᵀPw_k ≤ 1 (S-procedure, λ̄_i ≥ 0)."""
    x0v, Pm = _x0(ops, x0), _pointwise_P(ops, P)
    Wm = _weight(ops, W)
    W1, W2, W3 = ops.partition(Wm)
    pr = _Problem(ops, f"pointwise regret (3.32), W={W if isinstance(W, str) else 'user'}",
                  lmi)
    mu, lams = cp.Variable(), cp.Variable(ops.T, nonneg=True)
    a = mu * float(x0v @ W1 @ x0v) - cp.sum(lams)
    b_full = W2 @ x0v
    has_b = bool(np.any(b_full != 0))
    w_cols = slice(ops.n, ops.nd)
    blocks = _p_blocks(ops)
    D_terms = [(mu, W3)] + [(lams[i], _block_term(Pm, sl, W3.shape[0]))
                            for i, sl in enumerate(blocks)]
    y = pr.par.Y_x0(x0v)
    if not pr.try_banded(w_cols, D_terms, a=a, b_terms=[(mu, b_full)] if has_b else [], y=y):
        refusal = _pointwise_fallback(pr, mu, lams, a, y, W3, Pm, b_full if has_b else None,
                                      solver)
        if refusal is not None:
            return refusal
    pr.add_constraints(constraints, x0v, Pm)
    pr.extra = {"lambda": lams}
    return pr.solve(mu, lambda: mu.value, solver, _solver_opts(solver_opts),
                    certify=lambda Pu: ("lower_bound", _pointwise_lb(ops, Pu, x0v, Pm, Wm)))


def _pointwise_fallback(pr: _Problem, mu: cp.Variable, lams: cp.Variable, a: cp.Expression,
                        y: cp.Expression, W3: np.ndarray, Pm: np.ndarray,
                        b_full: np.ndarray | None, solver: str) -> SynthesisResult | None:
    """(3.32) outside banded coordinates: the chordal split for a block-diagonal W₃, else one
    dense cone (Σλ_iP_i + μW₃ is not diagonalizable jointly in (λ, μ)), refused with a status
    when Clarabel's dense KKT block would not fit in memory."""
    ops = pr.ops
    w_cols, blocks = slice(ops.n, ops.nd), _p_blocks(ops)
    if _is_block_diag(np.pad(W3, ((ops.n, 0), (ops.n, 0))), ops):
        Yw = pr.par.Y(w_cols)
        leaves = [Leaf(lams[i] * Pm + mu * W3[sl, sl], Yw[:, sl],
                       None if b_full is None else mu * b_full[sl])
                  for i, sl in enumerate(blocks)]
        pr.cons += arrow_lmi(pr.par.M, leaves, a=a, y=y, split=pr.split)
        return None
    refusal = _dense_cone_refusal(pr, 1 + pr.par.M + ops.p * ops.T, solver)
    if refusal is not None:
        return refusal
    D = mu * W3 + cp.bmat([[lams[i] * Pm if i == j else np.zeros((ops.p, ops.p))
                           for j in range(ops.T)] for i in range(ops.T)])
    D = 0.5 * (D + D.T)
    leaf = Leaf(D, pr.par.Y(w_cols), None if b_full is None else mu * b_full)
    pr.cons += arrow_lmi(pr.par.M, [leaf], a=a, y=y, split=False)
    return None


@_retry_outside_banded
def pointwise_dynamic_regret(ops: Operators, x0: object, P: object, *,
                             constraints: StateInputConstraints | None = None,
                             lmi: str = "banded", solver: str = "CLARABEL",
                             solver_opts: dict | None = None) -> SynthesisResult:
    """Theorem 3.12, SDP (3.34): γ̄* = min Σ_{i=0}^T λ̄_i, with (2/π)γ̄* ≤ R⁰_PWB ≤ γ̄* (3.36)."""
    x0v, Pm = _x0(ops, x0), _pointwise_P(ops, P)
    pr = _Problem(ops, "pointwise dynamic regret (3.34)", lmi)
    lams = cp.Variable(ops.T + 1, nonneg=True)
    w_cols, blocks = slice(ops.n, ops.nd), _p_blocks(ops)
    D_terms = [(lams[i + 1], _block_term(Pm, sl, ops.p * ops.T)) for i, sl in enumerate(blocks)]
    y = pr.par.Y_x0(x0v)
    if not pr.try_banded(w_cols, D_terms, a=lams[0], y=y):
        Yw = pr.par.Y(w_cols)
        leaves = [Leaf(lams[i + 1] * Pm, Yw[:, sl]) for i, sl in enumerate(blocks)]
        pr.cons += arrow_lmi(pr.par.M, leaves, a=lams[0], y=y, split=pr.split)
    pr.add_constraints(constraints, x0v, Pm)
    pr.extra = {"lambda": lams}
    total = cp.sum(lams)
    return pr.solve(total, lambda: total.value, solver, _solver_opts(solver_opts),
                    certify=lambda Pu: ("lower_bound", _pointwise_lb(ops, Pu, x0v, Pm, None)))


def _pointwise_lb(ops: Operators, Phi_u: np.ndarray, x0: np.ndarray, P: np.ndarray,
                  W: np.ndarray | None) -> float:
    """Certified lower bound on the pointwise worst case of Φ_u (verify.py; 20 starts)."""
    return pointwise_regret_lower_bound(ops, Phi_u, x0, P, W=W, starts=20, iters=200).value


# ----------------------------------------------------------------------------------------------
# baselines of Section 3.8 (SPEC 2.17 [Default])
# ----------------------------------------------------------------------------------------------
def h2(ops: Operators, x0: object, *, constraints: StateInputConstraints | None = None,
       constraint_P: object | None = None, omega: float | None = None,
       solver: str = "CLARABEL", solver_opts: dict | None = None) -> SynthesisResult:
    """SH2: min ‖C^{1/2}Φ⁰x₀‖² + ‖C^{1/2}Φ^w‖_F² (expected cost for white w with unit covariance).

    Written as ‖Y⁰x₀‖² + ‖Y^w‖_F² + x₀ᵀ𝒪₁x₀ + tr 𝒪₃; the level reported is that expected cost.
    """
    x0v = _x0(ops, x0)
    pr = _Problem(ops, "SH2", "split")
    O1, _, O3 = ops.O_parts
    const = float(x0v @ O1 @ x0v + np.trace(O3))
    Yw = pr.par.Y(slice(ops.n, ops.nd))
    obj = cp.sum_squares(pr.par.Y_x0(x0v)) + cp.sum_squares(Yw)
    pr.add_constraints(constraints, x0v, _opt_P(ops, constraint_P),
                       None if omega is None else _omega(omega))
    return pr.solve(obj, lambda: obj.value + const, solver, _solver_opts(solver_opts))


@_retry_outside_banded
def hinf(ops: Operators, *, x0: object | None = None,
         constraints: StateInputConstraints | None = None, constraint_P: object | None = None,
         omega: float | None = None, lmi: str = "banded", solver: str = "CLARABEL",
         solver_opts: dict | None = None) -> SynthesisResult:
    """SH∞: min γ s.t. γI − ΦᵀCΦ ⪰ 0 on the whole δ (SLP H∞); here γI − 𝒪 − YᵀY ⪰ 0."""
    pr = _Problem(ops, "SH-inf", lmi)
    gamma = cp.Variable()
    if not pr.try_banded(slice(0, ops.nd), [(gamma, np.eye(ops.nd)), (-1.0, ops.O)]):
        evals, U = np.linalg.eigh(ops.O)
        YU = pr.par.Y_times(slice(0, ops.nd), U)
        leaves = [Leaf(D, YU[:, sl]) for sl, D in diagonal_groups(gamma - evals, ops.p)]
        pr.cons += arrow_lmi(pr.par.M, leaves, split=pr.split)
    x0v = None if x0 is None else _x0(ops, x0)
    pr.add_constraints(constraints, x0v, _opt_P(ops, constraint_P),
                       None if omega is None else _omega(omega))
    return pr.solve(gamma, lambda: gamma.value, solver, _solver_opts(solver_opts),
                    certify=lambda Pu: ("exact", hinf_level(ops, Pu)))
