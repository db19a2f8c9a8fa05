"""A nonlinear RPI error set that holds: an incremental quadratic Lyapunov function with a
linear error feedback from an SDP over a polytopic bound of the Jacobians (thesis §6.5 and
§8.2, SPEC §2.31 "RPI set"), and the ellipsoidal terminal CBF of (6.17) made robust to the
same Jacobian bound; plus checks a user can run on *any* ``E``/``κ``/``h_f``.

**Setting.** ``x⁺ = f(x, u) + G w`` with ``∂f/∂u = B`` constant and, for every ``x`` of a
convex domain ``D``, ``∂f/∂x(x) ∈ conv{A_1, …, A_M}`` (a :class:`PolytopicLDI`). For the
kinematic bicycle the Jacobian is ``A0 + Σ_k a_k(x) E_k`` with four scalar functions
``a_k`` whose ranges on a box are intervals (:func:`balustrade.models.bicycle.jacobian_ldi`);
the ``A_i`` are the ``2⁴`` corners.

**Claim 1 (RPI).** Let ``E_P ≻ 0``, ``Y``, ``λ ∈ (0, 1)`` satisfy for every vertex ``A_i`` and
every vertex ``w^v`` of ``W``

    ``M_i,v = [[λE_P, 0, (A_iE_P+BY)ᵀ], [0, 1−λ, (Gw^v)ᵀ], [A_iE_P+BY, Gw^v, E_P]] ⪰ 0``,

and set ``P = E_P⁻¹``, ``K = Y P``, ``V(e) = eᵀPe``. Then for all ``z, x = z + e`` whose
segment lies in ``D`` (e.g. both in ``D``, ``D`` convex), every ``v``, and every ``w ∈ W``,
the error ``e⁺ = f(z+e, v+Ke) + Gw − f(z, v)`` satisfies ``V(e⁺) <= λV(e) + (1−λ)``; hence
``V(e) <= 1 ⇒ V(e⁺) <= 1``: ``E = {V <= 1}`` is RPI for the *nonlinear* error dynamics.

*Proof.* By the fundamental theorem of calculus along the segment (``f`` is C¹ on ``D``),
``f(z+e, v+Ke) − f(z, v) = Ā e + BKe`` with ``Ā = ∫₀¹ ∂f/∂x(z + se) ds`` (``∂f/∂u = B`` is
constant, so the input part is exact). Each integrand lies in the convex hull of the ``A_i``;
the integral of a hull-valued function over ``[0, 1]`` is in the (closed) hull, so
``Ā = Σ_i θ_i A_i`` with ``θ`` in the simplex. ``M`` is affine in ``A``, so
``Σ_i θ_i M_i,v = M(Ā)_v ⪰ 0``, and ``M(Ā)`` is affine in ``w^v`` too, so it holds for every
``w ∈ W = conv{w^v}`` (with ``(Gw)`` in place of ``Gw^v``). A Schur complement of
``M(Ā)_w`` with respect to ``E_P`` and the congruence ``diag(P, 1)`` give
``[[λP, 0], [0, 1−λ]] − [Ā+BK, Gw]ᵀ P [Ā+BK, Gw] ⪰ 0``; evaluating at ``(e, 1)`` yields
``V(e⁺) <= λ V(e) + (1−λ)``. ∎

Among the feasible ``(E_P, Y)`` the SDP minimizes the relative tightenings of all state and
input rows, as :func:`~balustrade.problems.rpi.rpi_sdp` does; ``λ`` is line-searched.

**Claim 2 (terminal CBF).** Let ``x_s, u_s`` be an equilibrium of ``f``, ``E_f ≻ 0``, ``Y_f``
with ``[[λ_f E_f, (A_iE_f+BY_f)ᵀ], [A_iE_f+BY_f, E_f]] ⪰ 0`` for every ``i``, the state rows
of ``X ⊖ E`` (tightened by ``Δ_{N−1}``) and the input rows of ``U ⊖ KE`` (scaled by
``1/sqrt(1+level)``) as in (6.17). With ``P_f = E_f⁻¹``, ``K_f = Y_f P_f``,
``h_f(x) = (x−x_s)ᵀP_f(x−x_s) − 1`` and ``π_f(x) = u_s + K_f(x−x_s)``: if ``S_f = {h_f <= 0}``
lies in ``D`` (it lies in ``X ⊖ E``, so ``X ⊆ D`` suffices), then for ``z ∈ S_f`` the nominal
``z⁺ = f(z, π_f(z))`` satisfies ``h_f(z⁺) + 1 <= λ_f (h_f(z) + 1)``, so ``S_f`` is invariant
with decrease for the *nonlinear* nominal model, ``S_f ⊆ X ⊖ E`` with the tightening
``Δ_{N−1}`` and ``π_f(S_f) ⊆ U ⊖ KE``. *Proof:* ``z⁺ − x_s = (Ā + BK_f)(z − x_s)`` with ``Ā``
the mean Jacobian along the segment from ``x_s`` to ``z`` (inside the convex ``S_f ⊆ D``),
then as in Claim 1 without ``w``. The thesis instead designs on the linearization at ``x_s``
and verifies afterwards [41, §IV]; the checks below do that verification for any design.

**Checks** (for any error set / terminal CBF, e.g. the linearization design as a negative
control): :func:`sampled_rpi_check` (random ``z``, ``v``, ``e ∈ ∂E``, ``w``),
:func:`worst_case_rpi_check` (the NLP ``max V(e⁺) − 1`` over ``z``, ``v``, ``V(e) <= 1``, ``w``
from many starts, on a CasADi target of :mod:`balustrade.backends.targets`),
:func:`sampled_terminal_check` and :func:`worst_case_terminal_check` (``max h_f(z⁺)`` over
``S_f``; also the decrease, the state rows and the input rows). A margin ``<= 0`` means no
counterexample was found; they test, the claims above prove.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from balustrade._checks import as_count, as_scalar, as_vector, check_instance
from balustrade.backends import compile, compile_synthesis, solve_synthesis
from balustrade.dsl.error_sets import ErrorSet, bounded_vertices
from balustrade.dsl.ocp import OCP
from balustrade.dsl.sets import Box, Ellipsoid, Polytope, Set
from balustrade.dsl.system import System
from balustrade.errors import BalustradeError
from balustrade.problems.incremental_rpi import (
    PolytopicLDI,
    incremental_rpi_sdp,
    robust_terminal_cbf_sdp,
)
from balustrade.problems.terminal_cbf import TerminalCBF, terminal_cbf_from


def _shifted(S: Polytope, center: np.ndarray, name: str) -> Polytope:
    return Polytope(S.H, S.h - S.H @ center, name=name)


def incremental_rpi(ldi: PolytopicLDI, W: Set, X: Polytope, U: Polytope, G: np.ndarray,
                    x_s: np.ndarray, u_s: np.ndarray | None = None,
                    lambdas: Sequence[float] | None = None, target: object = "sdp",
                    name: str = "E", min_axes: object = 1e-3) -> ErrorSet:
    """``E = {eᵀPe <= 1}`` and ``κ(e) = Ke`` of Claim 1 (module docstring), line-searching
    ``λ`` (default 19 values in ``(0, 1)``; ``min_axes``: :func:`incremental_rpi_sdp`);
    ``X``, ``U`` are centred at ``(x_s, u_s)`` for the objective. ``info``: ``lambda``,
    ``objective``, ``solve_time``, ``method``, ``domain`` (the box of states on which the
    Jacobian bound, hence the guarantee, holds), ``lmi_residual`` and ``proven_level``
    (:func:`proven_level`: the level ``c`` at which ``{V <= c}`` is RPI by the LMIs as
    solved; 1 when they hold exactly)."""
    n, m = ldi.B.shape
    x_s = as_vector(x_s, "incremental_rpi: x_s", n)
    u_s = np.zeros(m) if u_s is None else as_vector(u_s, "incremental_rpi: u_s", m)
    lambdas = list(lambdas) if lambdas is not None else list(np.linspace(0.05, 0.95, 19))
    for lv in lambdas:
        if not 0 < lv < 1:
            raise BalustradeError(f"incremental_rpi: lambdas: every λ must lie in (0, 1), "
                                  f"got {lv}")
    sdp = incremental_rpi_sdp(ldi, W, _shifted(X, x_s, "X-x_s"),
                              _shifted(U, u_s, "U-u_s"), G, min_axes)
    compiled = compile_synthesis(sdp, target)
    best, start = None, time.perf_counter()
    for lv in lambdas:
        sol = compiled.solve({"lambda": lv})
        if sol.ok and (best is None or sol.objective < best[0].objective):
            best = (sol, lv)
    if best is None:
        raise BalustradeError(
            f"incremental_rpi: no λ of {len(lambdas)} admits a common incremental quadratic "
            f"Lyapunov function on the domain {ldi.describe_domain()}; shrink the domain or "
            "the disturbance")
    sol, lv = best
    Ev = 0.5 * (sol["E"] + sol["E"].T)
    P = np.linalg.inv(Ev)
    P = 0.5 * (P + P.T)
    K = sol["Y"] @ P
    residual, level = proven_level(ldi, W, G, P, K, lv)
    return ErrorSet(Ellipsoid(P, name=name), K,
                    info={"objective": sol.objective, "lambda": lv,
                          "solve_time": time.perf_counter() - start,
                          "method": "incremental quadratic Lyapunov function over a "
                                    "polytopic LDI (Claim 1 of balustrade.design."
                                    "incremental_rpi)",
                          "domain": ldi.describe_domain(),
                          "lmi_residual": residual, "proven_level": level})


def proven_level(ldi: PolytopicLDI, W: Set, G: np.ndarray, P: np.ndarray, K: np.ndarray,
                 lam: float) -> tuple[float, float]:
    """What the solver's numbers prove (Claim 1 with the LMIs as solved, not as posed).

    ``η = max(0, −min eig D_i,v)`` over the Jacobian vertices ``A_i`` and the vertices
    ``w^v`` of ``W``, with ``D = [[λP, 0], [0, 1−λ]] − [A+BK, Gw]ᵀ P [A+BK, Gw]``. ``D`` is
    matrix-concave in ``(A, w)``, so ``D ⪰ −η I`` on the whole hull, and
    ``V(e⁺) <= (λ + η/μ) V(e) + (1 − λ + η)`` with ``μ = λ_min(P)``. Hence
    ``{V <= c}`` is RPI for ``c = (1 − λ + η) / (1 − λ − η/μ)`` (``c = 1`` when the LMIs hold
    exactly; ``inf`` if ``λ + η/μ >= 1``). Returns ``(η, c)``. The bicycle's design has
    ``η ≈ 2e-4`` (SDP tolerance against ``‖P‖ ≈ 4e4``): its ``E`` is proven RPI only as
    ``{V <= 1.005}``; the sampled and worst-case checks find ``E`` itself RPI with a 3 %
    margin (audit D, session 15)."""
    BK = ldi.B @ K
    Gw = bounded_vertices(W) @ np.asarray(G, dtype=float).T
    n = P.shape[0]
    eta = 0.0
    for A in ldi.vertices():
        for g in Gw:
            M = np.column_stack([A + BK, g])
            D = np.zeros((n + 1, n + 1))
            D[:n, :n], D[n, n] = lam * P, 1.0 - lam
            D -= M.T @ P @ M
            eta = max(eta, -float(np.linalg.eigvalsh(0.5 * (D + D.T))[0]))
    mu = float(np.linalg.eigvalsh(P)[0])
    rate = lam + eta / mu
    return eta, (float((1.0 - lam + eta) / (1.0 - rate)) if rate < 1.0 else float("inf"))


def robust_terminal_cbf(ldi: PolytopicLDI, X_E: Polytope, U_E: Polytope, x_s: np.ndarray,
                        delta_N: float = 0.0, level: float = 1.0,
                        decrease_factor: float = 0.99, target: object = "sdp"
                        ) -> TerminalCBF:
    """The terminal CBF of Claim 2 (module docstring): (6.17) with the invariance LMI at
    every Jacobian vertex, the state rows of ``X_E`` tightened by ``delta_N`` and the input
    rows of ``U_E`` scaled by ``1/sqrt(1 + level)`` (so ``γ_f >= level``), all centred at
    ``x_s`` (``u_s = 0``). ``P``, ``K`` act on ``x − x_s``."""
    n, m = ldi.B.shape
    x_s = as_vector(x_s, "robust_terminal_cbf: x_s", n)
    delta_N = as_scalar(delta_N, "robust_terminal_cbf: delta_N", low=0.0)
    level = as_scalar(level, "robust_terminal_cbf: level", low=0.0)
    decrease_factor = as_scalar(decrease_factor, "robust_terminal_cbf: decrease_factor",
                                0.0, 1.0, low_open=True)              # λ_f of Claim 2
    Xc, Uc = _shifted(X_E, x_s, "X_E-x_s"), U_E
    bx = Xc.h - delta_N
    bu = Uc.h / np.sqrt(1.0 + level)
    if np.any(bx <= 0) or np.any(bu <= 0):
        raise BalustradeError(f"robust_terminal_cbf: x_s must lie inside X_E tightened by "
                              f"delta_N and 0 inside U_E (state bounds {bx.tolist()}, input "
                              f"bounds {bu.tolist()})")
    sdp = robust_terminal_cbf_sdp(ldi, Xc.H, bx, Uc.H, bu, decrease_factor)
    sol = solve_synthesis(sdp, target)
    if not sol.ok:
        raise BalustradeError(f"robust_terminal_cbf: no solution ({sol.status}: "
                              f"{sol.message}) on the domain {ldi.describe_domain()}")
    return terminal_cbf_from(sol.values, Uc, decrease_factor, sol.status, sol.solve_time)


# -- checks -----------------------------------------------------------------------------------
@dataclass
class InvarianceCheck:
    """A check's result: ``margin`` is the largest violation found (``<= tol``: none);
    ``worst`` the point attaining it; ``parts`` the margins of each condition."""

    method: str
    margin: float
    worst: dict = field(default_factory=dict)
    parts: dict = field(default_factory=dict)
    count: int = 0
    failed_starts: int = 0
    tol: float = 1e-7

    @property
    def ok(self) -> bool:
        return bool(self.margin <= self.tol)

    def summary(self) -> dict:
        return {"method": self.method, "margin": float(self.margin), "ok": self.ok,
                "count": self.count, "failed_starts": self.failed_starts,
                "parts": {k: float(v) for k, v in self.parts.items()},
                "worst": {k: np.asarray(v).tolist() for k, v in self.worst.items()}}


def _ellipsoid_P(error: ErrorSet) -> np.ndarray:
    check_instance(error, ErrorSet, "RPI check: error")
    if not isinstance(error.E, Ellipsoid):
        raise BalustradeError(f"RPI check: the error set must be an Ellipsoid, got "
                              f"{type(error.E).__name__}")
    if error.K is None:
        raise BalustradeError("RPI check: the error set needs a linear feedback K")
    return np.asarray(error.E.P, dtype=float)


def _boundary(rng: np.random.Generator, P: np.ndarray, count: int) -> np.ndarray:
    """``count`` points of ``∂{eᵀPe <= 1}``, uniform in direction."""
    L = np.linalg.cholesky(np.linalg.inv(P))
    d = rng.standard_normal((count, P.shape[0]))
    d /= np.linalg.norm(d, axis=1)[:, None]
    return d @ L.T


def _fn(system: System) -> Callable:
    x, u, w = ca.SX.sym("x", system.nx), ca.SX.sym("u", system.nu), ca.SX.sym("w", system.nw)
    return ca.Function("f", [x, u, w], [system(x, u, w)])


def _rpi_args(block: str, system: System, error: ErrorSet, Z: Box, V: Polytope, W: Box,
              count: object, what: str) -> int:
    """The arguments of the RPI checks: types, dimensions (``Z`` ``nx``, ``V`` ``nu``, ``W``
    ``nw``, ``E`` ``nx``, ``K`` ``(nu, nx)``) and ``count >= 1`` (samples or starts), each
    wrong one a BalustradeError naming it before anything is evaluated (``samples=0`` ended
    in a CasADi assertion, a ``Z`` of the input's size in a numpy broadcast error; audit D,
    session 15)."""
    check_instance(system, System, f"{block}: system")
    check_instance(error, ErrorSet, f"{block}: error")
    check_instance(Z, Box, f"{block}: Z")
    check_instance(V, Polytope, f"{block}: V")
    check_instance(W, Box, f"{block}: W")
    for name, S, n, of in (("Z", Z, system.nx, "states"), ("V", V, system.nu, "inputs"),
                           ("W", W, system.nw, "disturbances"),
                           ("error.E", error.E, system.nx, "states")):
        if S.dim != n:
            raise BalustradeError(f"{block}: {name} has dimension {S.dim}, the system has "
                                  f"{n} {of}")
    if error.K is None or np.shape(error.K) != (system.nu, system.nx):
        raise BalustradeError(f"{block}: error.K must be a ({system.nu}, {system.nx}) linear "
                              f"feedback, got {None if error.K is None else np.shape(error.K)}")
    return as_count(count, f"{block}: {what}", low=1)


def sampled_rpi_check(system: System, error: ErrorSet, Z: Box, V: Polytope, W: Box,
                      samples: int = 20000, seed: int = 0) -> InvarianceCheck:
    """``max V(e⁺) − 1`` over random ``z ∈ Z``, ``v ∈ V``, ``e ∈ ∂E``, ``w ∈ W`` (``Z``, ``W``
    boxes, ``V`` a polytope such as ``U ⊖ KE``; half the ``w`` at vertices),
    ``e⁺ = f(z+e, v+Ke, w) − f(z, v, 0)``. Evaluated batched."""
    samples = _rpi_args("sampled_rpi_check", system, error, Z, V, W, samples, "samples")
    P = _ellipsoid_P(error)
    K = np.asarray(error.K, dtype=float)
    rng = np.random.default_rng(seed)
    zs, vs = Z.sample(samples, rng), V.sample(samples, rng)
    es = _boundary(rng, P, samples)
    ws = W.sample(samples, rng)
    half = samples // 2
    ws[:half] = np.where(rng.random((half, W.dim)) < 0.5, W.lb, W.ub)
    f = _fn(system).map(samples)
    x1 = np.asarray(f((zs + es).T, (vs + es @ K.T).T, ws.T))
    x0 = np.asarray(f(zs.T, vs.T, np.zeros((W.dim, samples))))
    en = (x1 - x0).T
    vals = np.einsum("ij,jk,ik->i", en, P, en) - 1.0
    k = int(np.argmax(vals))
    return InvarianceCheck("sampled", float(vals[k]),
                           {"z": zs[k], "v": vs[k], "e": es[k], "w": ws[k]},
                           {"V(e+)-1": float(vals[k])}, samples)


def worst_case_rpi_check(system: System, error: ErrorSet, Z: Box, V: Polytope, W: Box,
                         starts: int = 20, seed: int = 0, target: object = "exact"
                         ) -> InvarianceCheck:
    """The NLP ``max V(e⁺) − 1`` over ``z ∈ Z``, ``v ∈ V``, ``eᵀPe <= 1``, ``w ∈ W`` (a
    horizon-free :class:`~balustrade.dsl.ocp.OCP` on ``target``, default the ``"exact"``
    preset) from ``starts`` random starts; the margin is the best converged local maximum
    (a local solver: a lower bound on the true maximum, like sampling, but sharper).
    Starts whose solve did not succeed are counted in ``failed_starts``, not used."""
    starts = _rpi_args("worst_case_rpi_check", system, error, Z, V, W, starts, "starts")
    P = _ellipsoid_P(error)
    K = np.asarray(error.K, dtype=float)
    nx, nu, nw = system.nx, system.nu, system.nw
    ocp = OCP(name="worst_case_rpi")
    z = ocp.variable("z", nx, lb=Z.lb, ub=Z.ub)
    v = ocp.variable("v", nu)
    ocp.le(ca.mtimes(ca.DM(V.H), v), ca.DM(V.h), name="v_in_V")
    s = ocp.variable("s", nx)   # e = L⁻ᵀ s with P = L Lᵀ: eᵀPe = ‖s‖² (well scaled)
    w = ocp.variable("w", nw, lb=W.lb, ub=W.ub)
    L = np.linalg.cholesky(P)
    Linv_T = np.linalg.inv(L).T
    e = ca.mtimes(ca.DM(Linv_T), s)
    ocp.le(ca.sumsqr(s), 1.0, name="e_in_E")
    en = system(z + e, v + ca.mtimes(ca.DM(K), e), w) - system(z, v, ca.DM.zeros(nw))
    ocp.minimize(-ca.sumsqr(ca.mtimes(ca.DM(L.T), en)))
    compiled = compile(ocp, target)
    rng = np.random.default_rng(seed)
    es = _boundary(rng, P, starts)
    guesses = [{"z": Z.sample(1, rng)[0], "v": V.sample(1, rng)[0], "e": es[k],
                "w": W.sample(1, rng)[0]} for k in range(starts - starts // 2)]
    if starts // 2:  # the other half: the worst points of a sampled pre-pass
        pre = [sampled_rpi_check(system, error, Z, V, W, 200, seed + 1 + k)
               for k in range(starts // 2)]
        guesses += [c.worst for c in pre]
    best, worst, failed = -np.inf, {}, 0
    for guess in guesses:
        guess = {"z": guess["z"], "v": guess["v"], "s": L.T @ guess["e"], "w": guess["w"]}
        sol = compiled.solve({}, warm_start=guess)
        if not sol.success:
            failed += 1
            continue
        val = -float(sol.objective) - 1.0
        if val > best:
            best = val
            worst = {n: np.asarray(sol[n], dtype=float).reshape(-1) for n in "zvw"}
            worst["e"] = Linv_T @ np.asarray(sol["s"], dtype=float).reshape(-1)
    if not np.isfinite(best):
        raise BalustradeError(f"worst_case_rpi_check: none of {starts} starts converged")
    return InvarianceCheck("worst-case NLP", best, worst, {"V(e+)-1": best}, starts, failed)


@dataclass(frozen=True)
class TerminalSpec:
    """What the terminal checks need: ``h_f(x) = (x−x_s)ᵀP(x−x_s) − 1``, ``π_f(x) = K(x−x_s)``
    (``u_s = 0``), the tightened sets and ``Δ_{N−1}``, the decrease factor ``λ_f``."""

    P: np.ndarray
    K: np.ndarray
    x_s: np.ndarray
    X_E: Polytope
    U_E: Polytope
    delta_N: float = 0.0
    decrease_factor: float = 1.0


def _terminal_args(block: str, system: System, spec: TerminalSpec, count: object,
                   what: str) -> int:
    """The arguments of the terminal checks (as :func:`_rpi_args`): ``P`` ``(nx, nx)``,
    ``K`` ``(nu, nx)``, ``x_s`` ``(nx,)`` and ``count >= 1``."""
    check_instance(system, System, f"{block}: system")
    check_instance(spec, TerminalSpec, f"{block}: spec")
    nx, nu = system.nx, system.nu
    for name, value, shape in (("P", spec.P, (nx, nx)), ("K", spec.K, (nu, nx)),
                               ("x_s", spec.x_s, (nx,))):
        if np.shape(value) != shape:
            raise BalustradeError(f"{block}: spec.{name} must have shape {shape}, got "
                                  f"{np.shape(value)}")
    return as_count(count, f"{block}: {what}", low=1)


def _set_margins(spec: TerminalSpec) -> dict:
    """Exact support-function maxima over ``S_f`` of the state rows (with ``Δ``) and the
    input rows: ``max_{S_f} a(x) − b`` for every row."""
    Einv = np.linalg.inv(spec.P)
    xs = spec.x_s
    st = [float(a @ xs + np.sqrt(a @ Einv @ a) - (b - spec.delta_N))
          for a, b in zip(spec.X_E.H, spec.X_E.h)]
    inp = [float(np.sqrt(a @ spec.K @ Einv @ spec.K.T @ a) - b)
           for a, b in zip(spec.U_E.H, spec.U_E.h)]
    return {"state_rows": max(st), "input_rows": max(inp)}


def sampled_terminal_check(system: System, spec: TerminalSpec, samples: int = 20000,
                           seed: int = 0) -> InvarianceCheck:
    """Invariance of ``S_f = {h_f <= 0}`` under ``π_f`` for the nonlinear nominal model:
    ``max h_f(z⁺)`` over random ``z ∈ S_f`` (half on ``∂S_f``), the decrease
    ``max h_f(z⁺) + 1 − λ_f (h_f(z) + 1)``, and exactly the rows ``S_f ⊆ X_E ⊖ Δ``,
    ``π_f(S_f) ⊆ U_E``. ``margin`` is the largest of the four."""
    samples = _terminal_args("sampled_terminal_check", system, spec, samples, "samples")
    rng = np.random.default_rng(seed)
    d = _boundary(rng, spec.P, samples)
    d[samples // 2:] *= rng.random((samples - samples // 2, 1)) ** (1 / spec.P.shape[0])
    zs = spec.x_s + d
    us = d @ spec.K.T
    f = _fn(system).map(samples)
    zn = np.asarray(f(zs.T, us.T, np.zeros((system.nw, samples)))).T - spec.x_s
    Vn = np.einsum("ij,jk,ik->i", zn, spec.P, zn)
    V0 = np.einsum("ij,jk,ik->i", d, spec.P, d)
    parts = {"h_f(z+)": float(np.max(Vn - 1.0)),
             "decrease": float(np.max(Vn - spec.decrease_factor * V0)), **_set_margins(spec)}
    k = int(np.argmax(Vn))
    return InvarianceCheck("sampled", max(parts.values()), {"z": zs[k]}, parts, samples)


def worst_case_terminal_check(system: System, spec: TerminalSpec, starts: int = 20,
                              seed: int = 0, target: object = "exact") -> InvarianceCheck:
    """The NLPs ``max h_f(z⁺)`` and ``max h_f(z⁺) + 1 − λ_f(h_f(z) + 1)`` over ``z ∈ S_f``
    from ``starts`` random starts each (as :func:`worst_case_rpi_check`), plus the exact
    row margins of :func:`sampled_terminal_check`."""
    starts = _terminal_args("worst_case_terminal_check", system, spec, starts, "starts")
    nx, nw = system.nx, system.nw
    Pd = ca.DM(spec.P)
    L = np.linalg.cholesky(spec.P)
    Linv_T = np.linalg.inv(L).T
    parts, worst, failed = {}, {}, 0
    rng = np.random.default_rng(seed)
    for label, lam in (("h_f(z+)", 0.0), ("decrease", spec.decrease_factor)):
        ocp = OCP(name="worst_case_terminal")
        s = ocp.variable("s", nx)   # d = L⁻ᵀ s, P = L Lᵀ (as in worst_case_rpi_check)
        d = ca.mtimes(ca.DM(Linv_T), s)
        ocp.le(ca.sumsqr(s), 1.0, name="z_in_S_f")
        z = ca.DM(spec.x_s) + d
        zn = system(z, ca.mtimes(ca.DM(spec.K), d), ca.DM.zeros(nw)) - ca.DM(spec.x_s)
        ocp.minimize(-(ca.mtimes([zn.T, Pd, zn]) - lam * ca.mtimes([d.T, Pd, d])))
        compiled = compile(ocp, target)
        best = -np.inf
        for d0 in _boundary(rng, spec.P, starts):
            sol = compiled.solve({}, warm_start={"s": L.T @ d0})
            if not sol.success:
                failed += 1
                continue
            val = -float(sol.objective) - (1.0 if lam == 0.0 else 0.0)
            if val > best:
                best = val
                worst[label] = spec.x_s + Linv_T @ np.asarray(sol["s"], dtype=float).reshape(-1)
        if not np.isfinite(best):
            raise BalustradeError(f"worst_case_terminal_check: none of {starts} starts "
                                  f"converged ({label})")
        parts[label] = best
    parts.update(_set_margins(spec))
    return InvarianceCheck("worst-case NLP", max(parts.values()), worst, parts, 2 * starts,
                           failed)


__all__ = ["InvarianceCheck", "PolytopicLDI", "TerminalSpec", "incremental_rpi",
           "incremental_rpi_sdp", "proven_level", "robust_terminal_cbf", "sampled_rpi_check",
           "sampled_terminal_check", "worst_case_rpi_check", "worst_case_terminal_check"]
