"""Offline design of the homothetic-tube RAPSF (thesis Chapter 4, SPEC §2.20 [Default]):
the tube gain ``K`` for all vertices of ``Θ₀`` (robust LMI :func:`robust_gain_sdp` solved on a
synthesis target), a λ-contractive box ``𝕏₀`` checked by LPs, and the checks of
Assumption 4.11 as public functions users call in their own tests:

* :func:`check_rpi` — ``A_cl(θ^j)𝕏₀ ⊕ W ⊆ 𝕏₀`` for every vertex (``s_jr + w̄_r <= 1``);
* :func:`check_constraints` — ``(x, Kx) ∈ 𝒵`` on ``𝕏₀`` (``t_r <= 1``);
* :func:`check_assumption_4_11` — for every generator ``(z, α)`` of the terminal set there is
  ``(v, z⁺, α⁺)`` meeting (4.5c)–(4.5e) (one LP per generator; the default ``z = 0,
  0 <= α <= 1`` reduces to the two checks above).

The joint constraints ``𝒵 = {Fx + Gu <= 1}`` (4.5d) are the language's
:class:`~balustrade.dsl.joint.JointPolytope` passed as ``F`` with ``G=None`` (e.g.
``JointPolytope.product(X, U)``), or the two matrices ``F, G`` (the older spelling): both go
through :func:`joint_set`, so the same shape checks apply and bad shapes raise a
:class:`~balustrade.errors.ShapeError` naming ``F``/``G`` and both shapes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
import scipy.optimize

from balustrade._checks import as_matrix
from balustrade.backends import solve_synthesis
from balustrade.backends.lp import solve_lps
from balustrade.backends.solution import Status
from balustrade.dsl.joint import JointPolytope, as_joint
from balustrade.dsl.sets import Box, Polytope
from balustrade.dsl.sets_geometry import vertices as polytope_vertices
from balustrade.errors import BalustradeError
from balustrade.problems.rapsf import (
    TerminalSet,
    check_parametric_system,
    check_terminal,
    check_tube_sets,
    check_vertices,
    closed_loop_matrices,
    disturbance_map,
    model_matrices,
    robust_gain_sdp,
    tube_constants,
    unit_polytope,
)


def joint_set(F: np.ndarray | JointPolytope, G: np.ndarray | None, n: int, m: int,
              where: str) -> JointPolytope:
    """``𝒵`` of (4.5d) for a system with ``n`` states and ``m`` inputs: ``F`` itself when it
    is a :class:`~balustrade.dsl.joint.JointPolytope` (``G`` must be ``None``), else
    ``JointPolytope(F, G)`` (:func:`~balustrade.dsl.joint.as_joint`); blocks that do not fit
    ``n``/``m`` raise :class:`~balustrade.errors.ShapeError` naming ``F`` or ``G``."""
    return as_joint(F, G, where).check_dims(n, m, where)


def _gain(K: object, n: int, where: str) -> np.ndarray:
    """``K`` as an ``m × n`` matrix (``m`` its rows)."""
    return as_matrix(K, f"{where}: K (m × n, n = {n} states)", (None, n))


@dataclass
class CheckReport:
    """The outcome of an LP check: ``ok`` and the largest violation (``<= tol`` when ok)."""

    ok: bool
    worst: float
    details: dict = field(default_factory=dict)

    def __bool__(self) -> bool:
        return self.ok


#: ``method="auto"`` of :func:`robust_gain` solves the LMI up to this many vertices of Θ₀
#: (3 masses: 4 vertices, 0.04 s) and tries the certified centre LQR gain above it (8 masses:
#: 128 vertices, the LMI took > 400 s; the certified LQR gain 0.1 s)
LMI_MAX_VERTICES = 16


def robust_gain(system: object, vertices: np.ndarray, contraction: float = 0.95,
                target: object = "sdp", method: str = "auto") -> np.ndarray:
    """A tube gain ``K`` with one quadratic Lyapunov function of decay ``contraction`` for
    every ``θ`` in the hull of ``vertices`` (``Θ₀``; SPEC §2.20 [Default] "robust LQR or
    LMI for all vertices of Θ₀").

    * ``method="lmi"``: ``K = Y E⁻¹`` of :func:`~balustrade.problems.rapsf.robust_gain_sdp`
      (``min tr E``), one LMI per vertex, solved on the synthesis ``target``;
    * ``method="lqr"``: the LQR gain (``Q = I``, ``R = I``) of ``(A(θ_c), B(θ_c))`` at the
      centre ``θ_c`` (mean of the vertices) with its Riccati matrix ``P``, *certified* by
      :func:`quadratic_contraction` ``<= contraction`` at every vertex, else a
      :class:`~balustrade.errors.BalustradeError`;
    * ``method="auto"`` ([Default]): the LMI for at most :data:`LMI_MAX_VERTICES` vertices;
      above, the certified LQR gain, and the LMI only if its certificate fails.

    Why the certificate covers all of ``Θ₀``: with ``P = L Lᵀ``,
    ``A_clᵀ P A_cl ⪯ λ² P ⇔ ‖Lᵀ A_cl L⁻ᵀ‖₂ <= λ``. ``A_cl(θ) = A(θ) + B(θ)K`` is affine in
    ``θ`` (4.6) and the spectral norm is convex, so ``θ ↦ ‖Lᵀ A_cl(θ) L⁻ᵀ‖₂`` is convex and
    its maximum over the polytope ``Θ₀`` is attained at a vertex. The gain then meets the
    LMI of :func:`robust_gain_sdp` with ``E = c P⁻¹``, ``Y = K E`` (``c`` scaling ``E ⪰ I``):
    the same property, not the same (trace-optimal) ``E``."""
    V = check_vertices(vertices, check_parametric_system(system, "robust_gain")[2],
                       "robust_gain")
    if method not in ("auto", "lmi", "lqr"):
        raise BalustradeError(f"robust_gain: method must be 'auto', 'lmi' or 'lqr', got "
                              f"{method!r}")
    if method == "lqr" or (method == "auto" and len(V) > LMI_MAX_VERTICES):
        K, P = centre_lqr_gain(system, V)
        worst = quadratic_contraction(system, K, P, V)
        if worst <= contraction:
            return K
        if method == "lqr":
            raise BalustradeError(f"robust_gain: the centre LQR gain contracts xᵀPx only by "
                                  f"{worst:.4g} > {contraction} at a vertex of Θ₀; use "
                                  "method='lmi' or a contraction closer to 1")
    sol = solve_synthesis(robust_gain_sdp(system, V, contraction), target)
    if not sol.ok:
        raise BalustradeError(f"robust_gain: the robust LMI is not solvable with contraction "
                              f"{contraction} at the {len(V)} vertices "
                              f"of Θ₀ (status {sol.status}); try a contraction closer to 1")
    E = 0.5 * (sol["E"] + sol["E"].T)
    return np.asarray(sol["Y"]) @ np.linalg.inv(E)


def centre_lqr_gain(system: object, vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(K, P)``: the discrete LQR gain ``u = Kx`` (``Q = I``, ``R = I``) of
    ``(A(θ_c), B(θ_c))`` at the mean ``θ_c`` of ``vertices`` and the Riccati matrix ``P``."""
    n, m, _ = check_parametric_system(system, "centre_lqr_gain")
    A, B = model_matrices(system, np.mean(np.atleast_2d(vertices), axis=0))
    try:
        P = scipy.linalg.solve_discrete_are(A, B, np.eye(n), np.eye(m))
    except (np.linalg.LinAlgError, ValueError) as exc:
        raise BalustradeError(f"centre_lqr_gain: no stabilizing LQR gain at the centre of "
                              f"Θ₀ ({exc})") from exc
    K = -np.linalg.solve(np.eye(m) + B.T @ P @ B, B.T @ P @ A)
    return K, 0.5 * (P + P.T)


def quadratic_contraction(system: object, K: np.ndarray, P: np.ndarray,
                          vertices: np.ndarray) -> float:
    """``max_j ‖Lᵀ A_cl(θ^j) L⁻ᵀ‖₂`` with ``P = L Lᵀ``: the smallest ``λ`` with
    ``A_cl(θ)ᵀ P A_cl(θ) ⪯ λ² P`` at every vertex, hence on their hull (convexity,
    :func:`robust_gain`)."""
    try:
        L = np.linalg.cholesky(P)
    except np.linalg.LinAlgError as exc:
        raise BalustradeError("quadratic_contraction: P is not positive definite") from exc
    Linv = np.linalg.inv(L)
    return max(float(np.linalg.norm(L.T @ Acl @ Linv.T, 2))
               for Acl in closed_loop_matrices(system, K, vertices))


def contraction_factor(X0: Polytope, system: object, K: np.ndarray,
                       vertices: np.ndarray) -> float:
    """The smallest ``λ`` with ``A_cl(θ^j)𝕏₀ ⊆ λ𝕏₀`` for all vertices: ``max_jr s_jr``."""
    HX = unit_polytope(X0, "contraction_factor")
    return max(X0.support(row @ Acl) for Acl in closed_loop_matrices(system, K, vertices)
               for row in HX)


def contractive_box(system: object, K: np.ndarray, vertices: np.ndarray, W: Polytope,
                    F: np.ndarray | JointPolytope, G: np.ndarray | None = None,
                    iterations: int = 500) -> Box:
    """A λ-contractive box ``𝕏₀ = {|x| <= c b}`` for all vertices, RPI for ``W`` and inside
    ``𝒵`` (SPEC §2.20 [Default]).

    The shape ``b`` is the Perron vector of ``M = max_j |A_cl(θ^j)|`` (elementwise), found by
    power iteration; then ``λ = ρ(M) < 1`` is required, and the scale ``c`` is the largest
    with ``t_r <= 1``, which must exceed the smallest with ``λ + w̄_r/(c b_r) <= 1``.
    Raises when ``ρ(M) >= 1`` (no contractive box for this ``K``: use a polytope). ``𝒵``: a
    :class:`~balustrade.dsl.joint.JointPolytope` ``F`` (``G=None``) or the matrices ``F, G``."""
    n, m, _ = check_parametric_system(system, "contractive_box")
    K = _gain(K, n, "contractive_box")
    Z = joint_set(F, G, n, m, "contractive_box")
    M = np.max(np.abs(np.stack(closed_loop_matrices(system, K, vertices))), axis=0)
    M = M + 1e-9                                        # irreducible: a positive Perron vector
    b = np.ones(n)
    for _ in range(iterations):
        b = M @ b
        b = b / b.max()
    lam = float(np.max((M @ b) / b))
    if lam >= 1:
        raise BalustradeError(f"contractive_box: max_j |A_cl(θ^j)| has spectral radius "
                              f"{lam:.4g} >= 1: no λ-contractive box for this K (use a "
                              "polytope 𝕏₀ or another K)")
    E = disturbance_map(system, n)
    w_bar = np.array([W.support(E[i]) for i in range(n)])
    c_min = float(np.max(w_bar / ((1 - lam) * b)))
    FGK = Z.closed_loop(K)
    t_unit = np.abs(FGK) @ b
    c_max = float(1.0 / np.max(t_unit)) if np.max(t_unit) > 0 else np.inf
    if c_min > c_max:
        raise BalustradeError(f"contractive_box: the smallest RPI scaling {c_min:.4g} of the "
                              f"λ = {lam:.4g} contractive box exceeds the largest one inside "
                              f"𝒵 ({c_max:.4g}): W is too large for this K")
    return Box.symmetric(c_max * b, name="X0")


class Parallelotope(Polytope):
    """``{x : |T x| <= d}`` (``T`` invertible, ``d > 0``) as the unit polytope
    ``{[T; −T]/d · x <= 1}``, with the support in closed form:
    ``max_{|Tx| <= d} aᵀx = |aᵀT⁻¹| d`` (``y = Tx`` ranges over the box ``|y| <= d``), so
    the constants ``s_jr``, ``t_r`` of SPEC §2.20 need no LP."""

    def __init__(self, T: np.ndarray, d: np.ndarray, name: str = "X0"):
        T = np.atleast_2d(np.asarray(T, dtype=float))
        d = np.asarray(d, dtype=float).ravel()
        if T.ndim != 2 or T.shape[0] != T.shape[1] or d.size != T.shape[0]:
            raise BalustradeError(f"Parallelotope: T must be square and d one entry per row, "
                                  f"got T {T.shape}, d {d.shape}")
        if not np.all(np.isfinite(d)) or np.any(d <= 0):
            raise BalustradeError(f"Parallelotope: d must be finite and > 0, got {d}")
        if np.linalg.cond(T) > 1e12:
            raise BalustradeError("Parallelotope: T is not invertible (condition number "
                                  f"{np.linalg.cond(T):.3g})")
        object.__setattr__(self, "T", T)
        object.__setattr__(self, "d", d)
        object.__setattr__(self, "T_inv", np.linalg.inv(T))
        H = T / d[:, None]
        super().__init__(np.vstack([H, -H]), np.ones(2 * d.size), name=name)

    def support(self, a: np.ndarray) -> float:
        """``|aᵀT⁻¹| d`` (closed form; :class:`Polytope` solves an LP)."""
        a = np.asarray(a, dtype=float).ravel()
        if a.size != self.dim:
            raise BalustradeError(f"{self.name}.support(a): a has {a.size} entries, the set "
                                  f"has dimension {self.dim}")
        return float(np.abs(a @ self.T_inv) @ self.d)

    def support_l1_map(self) -> np.ndarray:
        """``M = T⁻¹ diag(d)`` with ``support(a) = ‖aᵀM‖₁`` for every ``a`` (the closed form
        above): a batch of supports — ``s_jr`` of SPEC §2.20 for all rows and vertices of
        ``Θ_k`` at once — is one matrix product and an absolute sum
        (:class:`balustrade.control.rapsf.RAPSF` reads it by this name)."""
        return self.T_inv * self.d[None, :]


def parallelotope_bases(system: object, K: np.ndarray, vertices: np.ndarray
                        ) -> list[np.ndarray]:
    """Candidate coordinates ``T`` for :func:`contractive_parallelotope`: the identity, the
    real modal basis of ``A_cl(θ_c)`` at the mean of ``vertices`` (eigenvectors; real and
    imaginary parts for a complex pair) and ``Lᵀ`` with ``P = LLᵀ`` the Lyapunov matrix of
    ``A_cl(θ_c)`` (``A_clᵀPA_cl − P = −I``), where they exist."""
    n = check_parametric_system(system, "parallelotope_bases")[0]
    A, B = model_matrices(system, np.mean(np.atleast_2d(vertices), axis=0))
    Ac = A + B @ np.asarray(K, dtype=float)
    bases = [np.eye(n)]
    ev, vec = np.linalg.eig(Ac)
    cols, used = [], set()
    for i, lam_i in enumerate(ev):
        if i in used:
            continue
        used.add(i)
        if abs(lam_i.imag) <= 1e-12:
            cols.append(vec[:, i].real)
            continue
        mate = [j for j in range(n) if j not in used and abs(ev[j] - np.conj(lam_i)) < 1e-9]
        used.update(mate[:1])
        cols += [vec[:, i].real, vec[:, i].imag]
    Vm = np.column_stack(cols) if len(cols) == n else None
    if Vm is not None and np.linalg.cond(Vm) < 1e8:
        bases.append(np.linalg.inv(Vm))
    if max(abs(ev)) < 1:
        P = scipy.linalg.solve_discrete_lyapunov(Ac.T, np.eye(n))
        try:
            bases.append(np.linalg.cholesky(0.5 * (P + P.T)).T)
        except np.linalg.LinAlgError:
            pass
    return bases


def contractive_parallelotope(system: object, K: np.ndarray, vertices: np.ndarray,
                              W: Polytope, F: np.ndarray | JointPolytope,
                              G: np.ndarray | None = None,
                              bases: list[np.ndarray] | None = None,
                              iterations: int = 500) -> Parallelotope:
    """A λ-contractive parallelotope ``𝕏₀ = {|Tx| <= c b}`` for all vertices, RPI for ``W``
    and inside ``𝒵``: :func:`contractive_box` in the coordinates ``y = Tx`` (``2n`` rows
    instead of a polytope's many, supports in closed form). For each ``T`` of ``bases``
    (default :func:`parallelotope_bases`) ``M = max_j |T A_cl(θ^j) T⁻¹|`` (elementwise),
    ``b`` its Perron vector and ``λ = ρ(M) < 1``: then ``|T A_cl(θ^j) x| <= M|Tx| <= λcb``,
    so ``A_cl(θ^j)𝕏₀ ⊆ λ𝕏₀`` at every vertex and, ``A_cl`` being affine in ``θ`` (4.6) and
    ``𝕏₀`` convex, on their hull. ``c`` is the largest scale with ``t_r <= 1`` and must
    exceed the smallest with ``λ + w̄_r/(c b_r) <= 1``; the first feasible ``T`` with the
    smallest ``λ`` is returned. Raises when no ``T`` gives one.

    Why (8 masses): no box in the original coordinates is contractive for any ``K`` (the
    position row ``p⁺ = p + T_s v`` has ``|A_cl|`` row sum ``> 1``: ``u`` does not act on
    it), and the contractive polytope has 104 rows, i.e. ``104·128`` LPs for ``s_jr`` per
    update of ``Θ_k``. ``𝒵``: a :class:`~balustrade.dsl.joint.JointPolytope` ``F``
    (``G=None``) or the matrices ``F, G``."""
    n, m, _ = check_parametric_system(system, "contractive_parallelotope")
    K = _gain(K, n, "contractive_parallelotope")
    FGK = joint_set(F, G, n, m, "contractive_parallelotope").closed_loop(K)
    Acls = closed_loop_matrices(system, K, vertices)
    E = disturbance_map(system, n)
    best, errors = None, []
    for T in bases if bases is not None else parallelotope_bases(system, K, vertices):
        T = np.asarray(T, dtype=float)
        Ti = np.linalg.inv(T)
        M = np.max(np.abs(np.stack([T @ A @ Ti for A in Acls])), axis=0) + 1e-9
        b = np.ones(n)
        for _ in range(iterations):
            b = M @ b
            b = b / b.max()
        lam = float(np.max((M @ b) / b))
        if lam >= 1:
            errors.append(f"ρ = {lam:.4g} >= 1")
            continue
        unit = Parallelotope(T, b)
        w_bar = np.array([max(W.support(row), W.support(-row)) for row in T @ E])  # |T E w|
        c_min = float(np.max(w_bar / ((1 - lam) * b)))
        t_unit = np.array([unit.support(row) for row in FGK])
        c_max = float(1.0 / np.max(t_unit)) if np.max(t_unit) > 0 else np.inf
        if c_min > c_max:
            errors.append(f"λ = {lam:.4g}: RPI scale {c_min:.4g} > {c_max:.4g} inside 𝒵")
            continue
        if best is None or lam < best[0]:
            best = (lam, T, c_max * b)
    if best is None:
        raise BalustradeError("contractive_parallelotope: no λ-contractive parallelotope for "
                              "this K (" + "; ".join(errors) + "): use a polytope 𝕏₀")
    return Parallelotope(best[1], best[2], name="X0")


def contractive_polytope(system: object, K: np.ndarray, vertices: np.ndarray, W: Polytope,
                         F: np.ndarray | JointPolytope, G: np.ndarray | None = None,
                         lam: float | None = None,
                         max_sweeps: int = 100, tol: float = 1e-9) -> Polytope:
    """A λ-contractive polytope ``𝕏₀ = {H_X x <= 1}`` for all vertices, RPI for ``W`` and
    inside ``𝒵`` (SPEC §2.20 [Default]): start from ``{(F + GK)x <= 1}`` and add the rows
    ``[H_X]_r A_cl(θ^j)/λ`` that are not redundant (one LP each) until none is added; then
    ``A_cl(θ^j)𝕏₀ ⊆ λ𝕏₀`` and the set is RPI when ``w̄_r <= 1 − λ``. ``lam`` defaults to
    ``(1 + max_j ρ(A_cl(θ^j)))/2``. Raises when the rows do not settle within
    ``max_sweeps`` sweeps (λ below the joint spectral radius) or ``W`` is too large.

    Speed (8 masses: 128 vertices, 40 starting rows): candidate rows are deduplicated
    first, screened by the bounding box of the current polytope (``support`` over the box
    ``>=`` over the polytope, so a row the box already satisfies is redundant without its
    LP), and the rest solved on one warm-started LP model (:func:`_supports`); the rows
    added are those of the plain loop (one ``linprog`` per candidate). ``𝒵``: a
    :class:`~balustrade.dsl.joint.JointPolytope` ``F`` (``G=None``) or the matrices ``F, G``."""
    n, m, _ = check_parametric_system(system, "contractive_polytope")
    K = _gain(K, n, "contractive_polytope")
    Z = joint_set(F, G, n, m, "contractive_polytope")
    Acls = closed_loop_matrices(system, K, vertices)
    if lam is None:
        lam = 0.5 * (1.0 + max(float(np.max(np.abs(np.linalg.eigvals(A)))) for A in Acls))
    if not 0 < lam < 1:
        raise BalustradeError(f"contractive_polytope: lam must lie in (0, 1), got {lam}")
    H = Z.closed_loop(K)
    H = H[np.linalg.norm(H, axis=1) > 1e-12]
    fresh = H
    for _ in range(max_sweeps):
        P = Polytope(H, np.ones(H.shape[0]), name="X0")
        added = []
        for a, value in zip(*_supports(P, _distinct(row @ A / lam for row in fresh
                                                    for A in Acls), tol), strict=True):
            if value > 1 + tol and not any(np.allclose(a, b) for b in added):
                added.append(a)
        if not added:
            break
        fresh = np.array(added)
        H = np.vstack([H, fresh])
    else:
        raise BalustradeError(f"contractive_polytope: no λ = {lam:.4g} contractive polytope "
                              f"after {max_sweeps} sweeps ({H.shape[0]} rows); try a "
                              "larger lam")
    X0 = _prune(Polytope(H, np.ones(H.shape[0]), name="X0"), tol)
    E = disturbance_map(system, n)
    w_bar = np.array([W.support(row @ E) for row in X0.H])
    if np.any(w_bar > 1 - lam):
        raise BalustradeError(f"contractive_polytope: W is too large: max_r w̄_r = "
                              f"{w_bar.max():.4g} > 1 − λ = {1 - lam:.4g}; 𝕏₀ ⊆ 𝒵 is not RPI")
    return X0


def _distinct(rows: object) -> list[np.ndarray]:
    """The rows without exact repeats, in order (e.g. ``[H_X]_r A_cl(θ^j)`` of a row that
    does not see θ is the same for every vertex: one LP instead of ``2^q``)."""
    seen: set[bytes] = set()
    out = []
    for a in rows:
        key = np.asarray(a, dtype=float).tobytes()
        if key not in seen:
            seen.add(key)
            out.append(a)
    return out


def _supports(P: Polytope, rows: list[np.ndarray], tol: float
              ) -> tuple[list[np.ndarray], np.ndarray]:
    """``(rows, upper bounds of their supports over P)``: the bound of its bounding box
    (``2n`` LPs, support over the box ``>=`` over ``P``) where that is ``<= 1 + tol`` (the
    row is redundant then, no LP needed), else the support itself (one warm-started LP
    model for all of them, :func:`~balustrade.backends.lp.solve_lps`; ``P.support`` for any
    it did not solve)."""
    if not rows:
        return rows, np.zeros(0)
    n = P.dim
    R = np.array(rows, dtype=float)
    ones = np.ones(P.H.shape[0])
    ext = solve_lps(np.vstack([np.eye(n), -np.eye(n)]), P.H, ones)
    if len(ext) == 2 * n and all(r.status is Status.OPTIMAL for r in ext):
        ub = np.array([r.value for r in ext[:n]])
        lb = -np.array([r.value for r in ext[n:]])
        value = np.maximum(R * ub, R * lb).sum(axis=1)
    else:
        value = np.full(len(R), np.inf)
    todo = np.flatnonzero(value > 1 + tol)
    res = solve_lps(R[todo], P.H, ones) if len(todo) else []
    for k, idx in enumerate(todo):
        ok = k < len(res) and res[k].status is Status.OPTIMAL
        value[idx] = res[k].value if ok else P.support(R[idx])
    return rows, value


def _prune(P: Polytope, tol: float) -> Polytope:
    """Drop the rows of ``{Hx <= 1}`` implied by the others (one LP each)."""
    keep = np.ones(P.H.shape[0], dtype=bool)
    for r in range(P.H.shape[0]):
        keep[r] = False
        rest = Polytope(P.H[keep], P.h[keep], name=P.name)
        keep[r] = rest.support(P.H[r]) > P.h[r] + tol
    return Polytope(P.H[keep], P.h[keep], name=P.name)


def check_rpi(X0: Polytope, system: object, K: np.ndarray, vertices: np.ndarray,
              W: Polytope, lam: float = 1.0, tol: float = 1e-9) -> CheckReport:
    """``A_cl(θ^j)𝕏₀ ⊕ W ⊆ λ𝕏₀`` for every vertex ``θ^j`` (i.e. ``s_jr + w̄_r <= λ``; one LP
    per row and vertex)."""
    n, _, q = check_parametric_system(system, "check_rpi")
    vertices = check_vertices(vertices, q, "check_rpi")
    check_tube_sets(system, X0, W, "check_rpi")
    F0 = np.zeros((1, n))
    c = tube_constants(X0, W, system, K, vertices, F0, np.zeros((1, np.shape(K)[0])))
    excess = c.s + c.w_bar[:, None] - lam
    worst = float(excess.max())
    return CheckReport(worst <= tol, worst, {"s": c.s, "w_bar": c.w_bar})


def check_constraints(X0: Polytope, F: np.ndarray | JointPolytope, G: np.ndarray | None,
                      K: np.ndarray, tol: float = 1e-9) -> CheckReport:
    """``(x, Kx) ∈ 𝒵`` for all ``x ∈ 𝕏₀`` (``t_r <= 1``; one LP per row of ``𝒵``). ``𝒵``:
    a :class:`~balustrade.dsl.joint.JointPolytope` ``F`` (``G=None``) or the matrices
    ``F, G``."""
    unit_polytope(X0, "check_constraints")
    K = _gain(K, X0.dim, "check_constraints")
    Z = joint_set(F, G, X0.dim, K.shape[0], "check_constraints")
    t = np.array([X0.support(row) for row in Z.closed_loop(K)])
    worst = float((t - 1.0).max())
    return CheckReport(worst <= tol, worst, {"t": t})


def check_assumption_4_11(system: object, X0: Polytope, W: Polytope, K: np.ndarray,
                          vertices: np.ndarray, F: np.ndarray | JointPolytope,
                          G: np.ndarray | None = None, terminal: TerminalSet | None = None,
                          tol: float = 1e-7) -> CheckReport:
    """Assumption 4.11 for ``𝕏_f`` and the vertices ``θ^j`` of ``Θ``: at every generator
    ``(z, α)`` of ``𝕏_f`` an LP finds ``v`` and ``(z⁺, α⁺) ∈ 𝕏_f`` with (4.5c), (4.5d). The
    feasible ``(z, α, v, z⁺, α⁺)`` form a polyhedron, so the generators suffice. The default
    terminal set ``z = 0, 0 <= α <= 1`` is checked at ``α = 1`` with ``v = 0, z⁺ = 0, α⁺ = 1``
    (:func:`check_rpi` and :func:`check_constraints`). ``𝒵``: a
    :class:`~balustrade.dsl.joint.JointPolytope` ``F`` (``G=None``) or the matrices ``F, G``."""
    n, m, q = check_parametric_system(system, "check_assumption_4_11")
    vertices = check_vertices(vertices, q, "check_assumption_4_11")
    check_tube_sets(system, X0, W, "check_assumption_4_11")
    check_terminal(terminal, n, "check_assumption_4_11")
    K = as_matrix(K, "check_assumption_4_11: K", (m, n))
    Z = joint_set(F, G, n, m, "check_assumption_4_11")
    if terminal is not None and terminal.has_generators:   # a hull (4.10): its own LPs
        from balustrade.design.rapsf_enlarge import check_enlarged_terminal
        return check_enlarged_terminal(system, X0, W, K, vertices, Z, None, terminal, tol)
    if terminal is None or terminal.H_T is None:
        rpi = check_rpi(X0, system, K, vertices, W, tol=tol)
        cons = check_constraints(X0, Z, None, K, tol=tol)
        return CheckReport(rpi.ok and cons.ok, max(rpi.worst, cons.worst),
                           {"rpi": rpi, "constraints": cons})
    c = tube_constants(X0, W, system, K, vertices, Z, None)
    H_T, h_T = np.asarray(terminal.H_T, float), np.asarray(terminal.h_T, float).ravel()
    Hz = np.hstack([H_T, h_T[:, None]])
    gens = polytope_vertices(np.vstack([Hz, -np.eye(n + 1)[n:]]),
                             np.concatenate([np.ones(H_T.shape[0]), [0.0]]),
                             "check_assumption_4_11: terminal set")
    worst = -np.inf
    for gen in gens:
        worst = max(worst, _terminal_lp(system, c, K, vertices, Z, H_T, h_T, gen[:n],
                                        gen[n], n, m))
    return CheckReport(worst <= tol, float(worst), {"generators": gens})


def _terminal_lp(system: object, c: object, K: np.ndarray, vertices: np.ndarray,
                 Z: JointPolytope, H_T: np.ndarray, h_T: np.ndarray,
                 z: np.ndarray, a: float, n: int, m: int) -> float:
    """The smallest uniform violation ``ε`` of (4.5c)–(4.5e) over ``(v, z⁺, α⁺)`` at the
    generator ``(z, α)`` (variables ``[v, z⁺, α⁺, ε]``, ``min ε``)."""
    HX = c.HX
    rows, rhs = [], []
    for j, th in enumerate(np.atleast_2d(vertices)):
        A, B = model_matrices(system, th)
        Acl = A + B @ K
        rows.append(np.hstack([HX @ B, -HX, -np.ones((HX.shape[0], 1)),
                               -np.ones((HX.shape[0], 1))]))
        rhs.append(-(HX @ Acl @ z + a * c.s[:, j] + c.w_bar))
    G = Z.G
    rows.append(np.hstack([G, np.zeros((G.shape[0], n + 1)), -np.ones((G.shape[0], 1))]))
    rhs.append(1.0 - Z.closed_loop(K) @ z - a * c.t)
    rows.append(np.hstack([np.zeros((H_T.shape[0], m)), H_T, h_T[:, None],
                           -np.ones((H_T.shape[0], 1))]))
    rhs.append(np.ones(H_T.shape[0]))
    cost = np.zeros(m + n + 2)
    cost[-1] = 1.0
    bounds = [(None, None)] * (m + n) + [(0, None), (None, None)]
    res = scipy.optimize.linprog(cost, A_ub=np.vstack(rows), b_ub=np.concatenate(rhs),
                                 bounds=bounds)
    if res.status != 0:
        raise BalustradeError(f"check_assumption_4_11: LP at generator {(z, a)} failed "
                              f"({res.message})")
    return float(res.fun)


__all__ = ["LMI_MAX_VERTICES", "CheckReport", "centre_lqr_gain", "check_assumption_4_11",
           "check_constraints", "check_rpi", "contraction_factor", "contractive_box",
           "contractive_parallelotope", "contractive_polytope", "joint_set", "Parallelotope",
           "parallelotope_bases", "quadratic_contraction", "robust_gain"]
