"""The robust adaptive predictive safety filter with linear homothetic tubes (thesis
Chapter 4, SPEC §2.18 and §2.20).

Dynamics affine in the parameter (4.6): ``x⁺ = A(θ)x + B(θ)u + w`` with
``A(θ) = A₀ + Σ_j θ_j A_j``, ``B(θ) = B₀ + Σ_j θ_j B_j``; any object with the attributes
``A0, A_list, B0, B_list`` (e.g. :class:`balustrade.dsl.system_parametric.ParametricLinearSystem`)
is accepted (``x⁺ = … + E w`` when it has ``E``). Tubes ``{z_i} ⊕ α_i 𝕏₀`` with
``𝕏₀ = {H_X x <= 1}`` and tube law ``κ(x, v) = Kx + v``; joint constraints ``𝒵 = {Fx + Gu <= 1}``,
the language's :class:`~balustrade.dsl.joint.JointPolytope` (every function below that takes
``F, G`` also takes ``𝒵`` in place of ``F`` with ``G=None``), imposed over the tubes by the
block :func:`~balustrade.dsl.joint.joint_constraint`.

* :func:`joint_constraints` — ``(F, G)`` of ``X × U`` normalized to right-hand side ``1``
  (:meth:`JointPolytope.product <balustrade.dsl.joint.JointPolytope.product>`);
* :func:`tube_constants` — the support-function constants ``w̄_r``, ``s_jr``, ``t_r`` of
  SPEC §2.20 (LPs over ``𝕏₀``; closed form for a box);
* :func:`rapsf_problem` — the QP (4.5) of SPEC §2.20 (also the Remark 4.6 shrunk horizon:
  pass ``N − k_inf``);
* :func:`robust_gain_sdp` — the robust (quadratic-stability) LMI for ``K`` over the vertices
  of ``Θ₀``, solved by :func:`balustrade.design.rapsf.robust_gain`.

Parametric vertex data. With ``vertices=None`` the vertices of ``Θ_k`` (``theta``, ``q × n_θ``)
and the constants ``s`` (``n_X × n_θ``) are *parameters*: a new ``Θ_k`` only changes parameter
values. They multiply decision variables (``A_cl(θ^j) z_i``, ``α_i s_jr``), so the rows (4.5c)
are affine in the variables with coefficients affine in the parameters; every target compiles
this form once: CasADi as any parameter, the convex backends' classify pass records the
constraint matrix as ``A(p) = A₀ + Σ_k p_k A_k``
(:class:`~balustrade.backends.passes.classify.Bilinear`), the direct backend (``"fast-convex"``)
updates the values of ``A(p)`` on a fixed sparsity pattern per solve and cvxpy keeps the
product DPP. With numeric ``vertices`` the vertex data are constants (a smaller problem per
``Θ_k``, rebuilt when it changes). :class:`balustrade.control.rapsf.RAPSF` uses the parametric
form by default (``vertex_data="parameters"``: one compile per horizon).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import casadi as ca
import numpy as np

from balustrade._checks import (
    as_float_array,
    as_matrix,
    as_vector,
    check_horizon,
    check_instance,
)
from balustrade.dsl import OCP, Polytope, squared_norm
from balustrade.dsl.joint import JointPolytope, as_joint, row_supports
from balustrade.dsl.synthesis import SynthesisProblem, bmat, trace
from balustrade.dsl.system import LinearSystem
from balustrade.errors import BalustradeError, NonFiniteError, ShapeError


# -- the parametric model (4.6) ---------------------------------------------------------
def check_parametric_system(system: object, where: str) -> tuple[int, int, int]:
    """``(n, m, q)`` of a system affine in θ (Assumption 4.1); errors name the wrong
    attribute or shape."""
    for attr in ("A0", "A_list", "B0", "B_list"):
        if not hasattr(system, attr):
            raise BalustradeError(f"{where}: system must be affine in θ (attributes A0, "
                                  f"A_list, B0, B_list); {type(system).__name__} has no "
                                  f"{attr!r}")
    A0 = as_matrix(system.A0, f"{where}: A0")
    n = A0.shape[0]
    if A0.shape != (n, n):
        raise ShapeError(f"{where}: A0", "a square matrix", A0.shape)
    B0 = as_matrix(system.B0, f"{where}: B0", (n, None))
    m = B0.shape[1]
    A_list, B_list = list(system.A_list), list(system.B_list)
    if len(A_list) != len(B_list):
        raise ShapeError(f"{where}: A_list and B_list", f"{len(A_list)} matrices each",
                         f"{len(A_list)} and {len(B_list)}", what="")
    for j, (Aj, Bj) in enumerate(zip(A_list, B_list, strict=True)):
        as_matrix(Aj, f"{where}: A_list[{j}]", (n, n))
        as_matrix(Bj, f"{where}: B_list[{j}]", (n, m))
    return n, m, len(A_list)


def disturbance_map(system: object, n: int) -> np.ndarray:
    """``E`` of ``x⁺ = A(θ)x + B(θ)u + E w`` (``I`` when the system has none)."""
    E = getattr(system, "E", None)
    return np.eye(n) if E is None else as_matrix(E, "disturbance_map: E", (n, None))


def model_matrices(system: object, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``A(θ)``, ``B(θ)`` of (4.6) at a numeric ``θ`` (``q`` entries, else
    :class:`~balustrade.errors.ShapeError`)."""
    theta = as_vector(theta, "model_matrices: theta", len(system.A_list))
    A = np.array(system.A0, dtype=float) + sum(
        (t * np.asarray(Aj, dtype=float) for t, Aj in zip(theta, system.A_list, strict=True)),
        np.zeros_like(np.asarray(system.A0, dtype=float)))
    B = np.array(system.B0, dtype=float) + sum(
        (t * np.asarray(Bj, dtype=float) for t, Bj in zip(theta, system.B_list, strict=True)),
        np.zeros_like(np.asarray(system.B0, dtype=float)))
    return A, B


def check_vertices(vertices: object, q: int, where: str) -> np.ndarray:
    """``vertices`` of ``Θ`` as a finite ``n_θ × q`` matrix with ``n_θ >= 1`` (rows are the
    vertices ``θ^j``); else a :class:`~balustrade.errors.BalustradeError` naming ``where``
    and the shapes (before any LP or solver runs)."""
    V = as_matrix(np.atleast_2d(as_float_array(vertices, f"{where}: vertices")),
                  f"{where}: vertices", (None, q))
    if V.shape[0] == 0:
        raise ShapeError(f"{where}: vertices", f"at least one vertex (an n_θ × {q} matrix, "
                         "n_θ >= 1)", V.shape, what="")
    return V


def closed_loop_matrices(system: object, K: np.ndarray, vertices: np.ndarray,
                         where: str = "closed_loop_matrices") -> list[np.ndarray]:
    """``A_cl(θ^j) = A(θ^j) + B(θ^j)K`` for each row ``θ^j`` of ``vertices`` (checked by
    :func:`check_vertices`: ``n_θ >= 1`` rows of width ``q``)."""
    out = []
    for th in check_vertices(vertices, len(system.A_list), where):
        A, B = model_matrices(system, th)
        out.append(A + B @ K)
    return out


def parameter_vertices(Theta: Polytope) -> np.ndarray:
    """Vertices of ``Θ`` as rows (``2^q`` for a box, in a fixed order)."""
    check_instance(Theta, Polytope, "parameter_vertices: Theta")
    return Theta.vertices()


# -- 𝒵 and the support-function constants of SPEC §2.20 -------------------------------
def joint_constraints(X: Polytope, U: Polytope) -> tuple[np.ndarray, np.ndarray]:
    """``𝒵 = X × U`` as ``{Fx + Gu <= 1}`` (every row divided by its bound, which must be
    positive: the origin inside ``X`` and ``U``): the blocks ``(F, G)`` of
    :meth:`JointPolytope.product <balustrade.dsl.joint.JointPolytope.product>`."""
    check_instance(X, Polytope, "joint_constraints: X")
    check_instance(U, Polytope, "joint_constraints: U")
    Z = JointPolytope.product(X, U)
    return Z.F, Z.G


def check_tube_sets(system: object, X0: Polytope, W: Polytope, where: str) -> None:
    """``𝕏₀`` a polytope in the state space (dimension ``n``) and ``W`` one of the
    disturbance's dimension (the columns of ``E``, ``n`` without one); else a
    :class:`~balustrade.errors.ShapeError` naming ``X0``/``W`` and the dimensions, before
    any support LP runs."""
    n = check_parametric_system(system, where)[0]
    check_instance(X0, Polytope, f"{where}: X0")
    if X0.dim != n:
        raise ShapeError(f"{where}: X0", f"dimension {n} (the state)", f"dimension {X0.dim}",
                         what="")
    check_instance(W, Polytope, f"{where}: W")
    nw = disturbance_map(system, n).shape[1]
    if W.dim != nw:
        raise ShapeError(f"{where}: W", f"dimension {nw} (the disturbance)",
                         f"dimension {W.dim}", what="")


def unit_polytope(X0: Polytope, where: str) -> np.ndarray:
    """``H_X`` of ``𝕏₀ = {H_X x <= 1}`` (rows of ``X0`` divided by their positive bounds)."""
    check_instance(X0, Polytope, f"{where}: X0")
    if np.any(X0.h <= 0):
        raise BalustradeError(f"{where}: X0 must contain the origin in its interior (row "
                              f"bounds {X0.h.tolist()})")
    return X0.H / X0.h[:, None]


@dataclass(frozen=True)
class TubeConstants:
    """The constants of SPEC §2.20: ``w_bar[r] = max_{w∈W} [H_X]_r w``,
    ``s[r, j] = max_{x∈𝕏₀} [H_X]_r A_cl(θ^j) x`` and ``t[r] = max_{x∈𝕏₀} [F+GK]_r x``."""

    HX: np.ndarray
    w_bar: np.ndarray
    s: np.ndarray
    t: np.ndarray


def support_rows(X0: Polytope, D: np.ndarray, X0_vertices: np.ndarray | None = None
                 ) -> np.ndarray:
    """``max_{x∈𝕏₀} d_r x`` for every row ``d_r`` of ``D``: one LP per row, in closed form
    for a :class:`~balustrade.dsl.sets.Box`, or as ``max_v d_r x^v`` over the vertices of
    ``𝕏₀`` when they were enumerated once (``X0_vertices``, rows; same values, a matrix
    product instead of LPs — the per-step update of ``s`` for small ``n``). The same
    computation as ``t`` of (4.5d): :func:`balustrade.dsl.joint.row_supports`."""
    return row_supports(D, X0, X0_vertices, "support_rows")


def s_constants(X0: Polytope, system: object, K: np.ndarray, vertices: np.ndarray,
                X0_vertices: np.ndarray | None = None) -> np.ndarray:
    """``s[r, j]`` (one LP per row and vertex, closed form for a box ``𝕏₀``, or over the
    enumerated vertices of ``𝕏₀``, :func:`support_rows`); recompute whenever the vertices of
    ``Θ_k`` change."""
    HX = unit_polytope(X0, "s_constants")
    Acls = closed_loop_matrices(system, K, vertices)
    return np.column_stack([support_rows(X0, HX @ Acl, X0_vertices) for Acl in Acls])


def tube_constants(X0: Polytope, W: Polytope, system: object, K: np.ndarray,
                   vertices: np.ndarray, F: np.ndarray | JointPolytope,
                   G: np.ndarray | None) -> TubeConstants:
    """All constants of SPEC §2.20 for the vertices ``θ^j`` (rows of ``vertices``); ``𝒵``
    given as matrices ``F, G`` or as a :class:`~balustrade.dsl.joint.JointPolytope`
    ``F`` with ``G=None``."""
    check_tube_sets(system, X0, W, "tube_constants")
    HX = unit_polytope(X0, "tube_constants")
    E = disturbance_map(system, HX.shape[1])
    w_bar = np.array([W.support(row @ E) for row in HX])
    Z = as_joint(F, G, "tube_constants").check_dims(HX.shape[1], np.shape(K)[0],
                                                    "tube_constants")
    t = Z.feedback_support(K, X0)
    return TubeConstants(HX, w_bar, s_constants(X0, system, K, vertices), t)


# -- exact sharing of tube rows between vertices ------------------------------------------------
def row_dependence(system: object, X0: Polytope) -> np.ndarray:
    """``D[r, k]``: whether tube row ``r`` of (4.5c) depends on ``θ_k`` at all, i.e.
    ``[H_X]_r A_k ≠ 0`` or ``[H_X]_r B_k ≠ 0`` (exact zeros only; then also
    ``[H_X]_r (A_k + B_k K) = 0``, so ``s_jr`` does not depend on ``θ_k`` either). For the
    mass–spring–damper chain a spring ``θ_k`` acts only on the velocities of its two masses,
    so rows of ``H_X`` on positions (or on far masses) do not depend on it."""
    HX = unit_polytope(X0, "row_dependence")
    cols = [np.any(HX @ np.asarray(Ak, dtype=float) != 0, axis=1)
            | np.any(HX @ np.asarray(Bk, dtype=float) != 0, axis=1)
            for Ak, Bk in zip(system.A_list, system.B_list, strict=True)]
    return np.column_stack(cols) if cols else np.zeros((HX.shape[0], 0), dtype=bool)


def shared_rows(dependence: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """``rep[r, j]``: the first vertex ``j' <= j`` whose coordinates ``θ^{j'}_k`` equal
    ``θ^j_k`` (exactly) for every ``k`` that row ``r`` depends on (:func:`row_dependence`);
    ``theta`` is ``q × n_θ`` (vertices as columns). Row ``r`` of (4.5c) for vertex ``j`` is
    then the same row as for ``rep[r, j]`` whenever the constants ``s_rj`` agree too
    (:func:`rows_shared`), so (4.5) needs it once: the same feasible set, fewer rows (for a
    box ``Θ`` a row depending on ``d`` of the ``q`` parameters appears ``2^d`` times, not
    ``2^q``)."""
    dependence = np.asarray(dependence, dtype=bool)
    theta = np.atleast_2d(np.asarray(theta, dtype=float))
    n_r, n_th = dependence.shape[0], theta.shape[1]
    rep = np.tile(np.arange(n_th), (n_r, 1))
    for r in range(n_r):
        sub = theta[dependence[r]]                                 # (|S_r|, n_θ)
        for j in range(n_th):
            same = np.all(sub[:, :j] == sub[:, j:j + 1], axis=0)
            hits = np.flatnonzero(same)
            if hits.size:
                rep[r, j] = hits[0]
    return rep


def rows_shared(rep: np.ndarray, dependence: np.ndarray, theta: np.ndarray, s: np.ndarray
                ) -> bool:
    """Whether the vertex data ``theta`` (``q × n_θ``) and ``s`` (``n_X × n_θ``) make every
    row dropped by ``rep`` (:func:`shared_rows`) an exact copy of the row it was merged
    into: ``θ^j_k = θ^{rep}_k`` for the ``k`` the row depends on and ``s_rj = s_r,rep``.
    Only then may the problem built with ``shared=rep`` be solved with these data."""
    theta = np.atleast_2d(np.asarray(theta, dtype=float))
    s = np.atleast_2d(np.asarray(s, dtype=float))
    if rep.shape != s.shape or theta.shape[1] != rep.shape[1]:
        return False
    rows = np.arange(rep.shape[0])[:, None]
    if not np.array_equal(s, s[rows, rep]):
        return False
    same = theta[:, None, :] == theta[:, rep]                    # (q, n_X, n_θ)
    used = np.asarray(dependence, dtype=bool).T[:, :, None]       # (q, n_X, 1)
    return bool(np.all(same | ~used))


# -- the QP (4.5) of SPEC §2.20 -------------------------------------------------------------
@dataclass(frozen=True)
class TerminalSet:
    """``𝕏_f = {(z, α) : H_T z + h_T α <= 1}`` (4.5e); ``None`` fields mean the §4.7 default
    ``z_N = 0, 0 <= α_N <= 1``.

    With generators (:meth:`from_generators`; thesis (4.10), SPEC §2.22) the set is the convex
    hull ``co({(Z[:, g], a[g])}_g ∪ 𝕏_f)`` of the generator pairs and the base set ``𝕏_f``
    above, imposed in (4.5) in the perspective form of SPEC §2.22:
    ``(z_N, α_N) = Σ_g λ_g (Z_g, a_g) + (z', α')`` with ``λ >= 0``, ``λ_f >= 0``,
    ``Σλ_g + λ_f = 1`` and ``(z', α')`` in ``λ_f 𝕏_f`` (``H_T z' + h_T α' <= λ_f 1``,
    ``α' >= 0``; for the default ``z' = 0, 0 <= α' <= λ_f``). ``capacity`` (set by
    :meth:`slot`) makes the generators a parameter ``terminal_generators`` of shape
    ``(n + 1) × capacity`` (rows ``[Z; a]``; pad unused columns with ``(0, 0)``, which every
    such set contains) so that a growing generator list does not change the compiled problem.
    """

    H_T: np.ndarray | None = None
    h_T: np.ndarray | None = None
    Z: np.ndarray | None = None
    a: np.ndarray | None = None
    capacity: int | None = None

    @classmethod
    def from_generators(cls, Z: np.ndarray, a: np.ndarray,
                        base: TerminalSet | None = None) -> TerminalSet:
        """``co({(Z[:, g], a[g])} ∪ base)``: ``Z`` is ``n × G`` (translations as columns),
        ``a`` the ``G`` dilations (``>= 0``); ``base`` an H-representation or ``None`` (the
        default set). Wrong shapes → :class:`~balustrade.errors.ShapeError`."""
        Z = np.asarray(Z, dtype=float)
        if Z.ndim != 2:
            raise ShapeError("TerminalSet.from_generators: Z", "an n × G matrix (columns "
                             "are the translations z_g)", Z.shape)
        a = np.asarray(a, dtype=float)
        if a.ndim > 2 or a.size != Z.shape[1] or (a.ndim == 2 and 1 not in a.shape):
            raise ShapeError("TerminalSet.from_generators: a", (Z.shape[1],), a.shape)
        a = a.reshape(-1)
        if not (np.all(np.isfinite(Z)) and np.all(np.isfinite(a))):
            raise NonFiniteError("TerminalSet.from_generators: Z and a must be finite")
        if np.any(a < 0):
            raise BalustradeError(f"TerminalSet.from_generators: dilations a must be >= 0, "
                                  f"got min {a.min():.3g}")
        H_T, h_T = (None, None) if base is None else (base.H_T, base.h_T)
        if base is not None and base.has_generators:
            raise BalustradeError("TerminalSet.from_generators: base must be an "
                                  "H-representation or the default set, not a hull")
        if H_T is not None and np.shape(H_T)[1] != Z.shape[0]:
            raise ShapeError("TerminalSet.from_generators: Z", f"{np.shape(H_T)[1]} rows "
                             "(the columns of base.H_T)", Z.shape)
        return cls(H_T, h_T, Z, a)

    @property
    def has_generators(self) -> bool:
        """Whether the set is a hull of generators (numeric or a parameter slot)."""
        return self.Z is not None or self.capacity is not None

    @property
    def generators(self) -> np.ndarray:
        """The numeric generator pairs as columns ``[Z; a]`` (``n + 1 × G``; ``G = 0``
        without generators)."""
        if self.Z is None:
            n = 0 if self.H_T is None else np.shape(self.H_T)[1]
            return np.zeros((n + 1, 0))
        return np.vstack([self.Z, self.a[None, :]])

    def slot(self, capacity: int) -> TerminalSet:
        """The same base with ``capacity`` generators as the parameter
        ``terminal_generators`` (the compiled form of a growing hull)."""
        capacity = int(capacity)
        if capacity < 1:
            raise BalustradeError(f"TerminalSet.slot: capacity must be positive, got "
                                  f"{capacity}")
        return TerminalSet(self.H_T, self.h_T, None, None, capacity)


def rapsf_problem(system: object, X0: Polytope, F: np.ndarray | JointPolytope,
                  G: np.ndarray | None, W: Polytope,
                  K: np.ndarray, N: int, n_vertices: int | None = None,
                  vertices: np.ndarray | None = None, terminal: TerminalSet | None = None,
                  X0_vertices: np.ndarray | None = None, shared: np.ndarray | None = None,
                  factored: bool | None = None, staged: bool = False,
                  name: str = "rapsf") -> OCP:
    """(4.5) with homothetic tubes (SPEC §2.20):

    ``min ‖u_p − (K x_k + v_0)‖²`` over ``z (n × N+1)``, ``alpha (1 × N+1) >= 0``, ``v (m × N)``
    s.t. (4.5b) ``H_X(x_k − z_0) <= α_0 1``; (4.5c) for every vertex ``θ^j`` and step ``i``
    ``H_X(A_cl(θ^j) z_i + B(θ^j) v_i − z_{i+1}) + α_i s_j + w̄ <= α_{i+1} 1``; (4.5d)
    ``(F + GK) z_i + α_i t + G v_i <= 1`` (the block
    :func:`~balustrade.dsl.joint.joint_constraint` over the homothetic tubes of ``𝕏₀``);
    (4.5e) the terminal set. ``𝒵`` is ``F`` when it is a
    :class:`~balustrade.dsl.joint.JointPolytope` (``G=None``), else ``{F x + G u <= 1}``.

    Parameters: ``x0``, ``u_p`` and, when ``vertices`` is ``None``, ``theta`` (``q × n_θ``,
    the vertices of ``Θ_k`` as columns; ``n_θ = n_vertices``, default ``2^q`` for a box) and
    ``s`` (``n_X × n_θ``, :func:`s_constants`). With numeric ``vertices`` (rows) they are
    constants. The Remark 4.6 variant is this problem with the shrunk horizon ``N − k_inf``.
    ``X0_vertices`` (optional, the vertices of ``𝕏₀`` as rows) replaces the LPs of the
    constants by maxima over them (:func:`support_rows`).

    ``shared`` (``n_X × n_θ`` integers, :func:`shared_rows`; parametric vertex data only)
    drops row ``r`` of vertex ``j`` when ``shared[r, j] != j``: it is the row of vertex
    ``shared[r, j]`` whenever the data pass :func:`rows_shared`, which the caller must check
    before each solve (else solve the problem built without ``shared``). With numeric
    ``vertices`` the duplicates are found and dropped from the data themselves. Either way
    the feasible set and the optimum are those of the full (4.5).

    ``factored`` writes (4.5c) with the vertex-independent part as variables of its own,
    ``y_i = H_X(A_cl,0 z_i + B_0 v_i − z_{i+1})`` (``tube_offset``, one equality row each),
    and the θ part on the columns ``c`` of ``(z_i, v_i)`` that some ``A_cl,k``/``B_k``
    uses: ``y_ir + Σ_c (Σ_k θ^j_k [H_X]_r M_k[:, c]) w_ic + α_i s_rj + w̄_r <= α_{i+1}``
    with ``M_k = [A_k + B_k K, B_k]`` (the same rows, exactly: ``y`` is defined by
    equalities). Each of the ``n_X n_θ N`` rows then has ``3 + |c|`` nonzeros instead of
    those of ``[H_X]_r [A_cl(θ), B(θ), −I]`` (8 masses, a dense ``H_X``: 11 instead of
    ~42). ``None`` (default): factored when the factored rows, with those defining ``y``,
    have at most half the nonzeros of the plain ones (:func:`factored_pays`).

    ``staged`` writes (4.5) in stage order (:func:`_staged_variables`): ``(ẑ_{i+1},
    α̂_{i+1})`` become variables of stage ``i`` (``z_next``, ``alpha_next``) tied to
    ``(z_{i+1}, α_{i+1})`` by equality rows tagged ``dynamics``, so that every row of
    (4.5c) is local to one stage and the structure-exploiting targets (the stage-order
    pass) accept the problem; same feasible set and optimum. Measured slower than
    ``"fast-convex"`` on the chain (docs/adaptive.md), so :class:`RAPSF` does not use it.
    """
    n, m, q = check_parametric_system(system, name)
    N = check_horizon(N, name)
    K = as_matrix(K, f"{name}: K", (m, n))
    Z = as_joint(F, G, name).check_dims(n, m, name)
    HX = unit_polytope(X0, name)
    check_instance(W, Polytope, f"{name}: W")
    E = disturbance_map(system, n)
    if W.dim != E.shape[1]:
        raise ShapeError(f"{name}: W", f"dimension {E.shape[1]}", f"dimension {W.dim}")
    w_bar = np.array([W.support(row @ E) for row in HX])                 # w̄_r
    if staged:
        ocp, z, alpha, v, z_next, a_next = _staged_variables(system, n, m, N, name)
    else:
        ocp = OCP(None, N, name=name)
        z = ocp.variable("z", n, N + 1, role="state")
        alpha = ocp.variable("alpha", 1, N + 1, lb=0.0)
        v = ocp.variable("v", m, N, role="input")
        z_next, a_next = z[:, 1:], alpha[:, 1:]
    x0 = ocp.parameter("x0", n)
    u_p = ocp.parameter("u_p", m)
    if vertices is None:
        n_th = 2 ** q if n_vertices is None else int(n_vertices)
        if n_th < 1:
            raise BalustradeError(f"{name}: n_vertices must be positive, got {n_vertices}")
        theta = ocp.parameter("theta", q, n_th)
        s = ocp.parameter("s", HX.shape[0], n_th)
        thetas = [theta[:, j] for j in range(n_th)]
        if shared is None:
            keep = np.ones((HX.shape[0], n_th), dtype=bool)
        else:
            shared = _checked_shared(shared, (HX.shape[0], n_th), name)
            keep = shared == np.arange(n_th)[None, :]
    else:
        V = np.atleast_2d(np.asarray(vertices, dtype=float))
        if V.shape[1] != q:
            raise ShapeError(f"{name}: vertices", f"rows of length q = {q}", V.shape)
        if shared is not None:
            raise BalustradeError(f"{name}: shared is for parametric vertex data; with "
                                  "numeric vertices the duplicate rows are dropped anyway")
        thetas = [ca.DM(th) for th in V]
        s_num = s_constants(X0, system, K, V, X0_vertices)
        rep = shared_rows(row_dependence(system, X0), V.T)
        keep = rep == np.arange(len(V))[None, :]
        if not rows_shared(rep, row_dependence(system, X0), V.T, s_num):
            keep[:] = True
        s = ca.DM(s_num)
    A_j, B_j = _symbolic_models(system, thetas)
    H, Kd = ca.DM(HX), ca.DM(K)
    one = ca.DM.ones(HX.shape[0], 1)
    ocp.le(ca.mtimes(H, x0 - z[:, 0]), alpha[0] * one, name="initial_tube", tag="tube")  # (4.5b)
    if factored is None:
        factored = factored_pays(system, X0, K, keep)
    if factored:
        _tube_rows_factored(ocp, system, HX, K, thetas, s, w_bar, keep, z, alpha, v, N,
                            z_next, a_next)
    _mark_row_groups(ocp, keep, N)
    for j, (A, B) in enumerate(zip(A_j, B_j, strict=True)):                             # (4.5c)
        if factored:
            break
        r_j = np.flatnonzero(keep[:, j]).tolist()    # rows not shared with an earlier vertex
        if not r_j:
            continue
        Acl = A + ca.mtimes(B, Kd)
        Hj, one_j, wb_j = ca.DM(HX[r_j]), ca.DM.ones(len(r_j), 1), ca.DM(w_bar[r_j])
        rows = [ca.mtimes(Hj, ca.mtimes(Acl, z[:, i]) + ca.mtimes(B, v[:, i]) - z_next[:, i])
                + alpha[i] * s[r_j, j] + wb_j - a_next[i] * one_j for i in range(N)]
        ocp.le(ca.vertcat(*rows), name=f"tube_vertex_{j}", tag="tube")
    ocp.joint_constraint(Z, z, v, feedback=K, tube=(alpha, X0), tube_vertices=X0_vertices,
                         name="tube_constraints")                                       # (4.5d)
    _terminal(ocp, z[:, N], alpha[N], terminal, n, name)                                 # (4.5e)
    ocp.minimize(squared_norm(u_p - (ca.mtimes(Kd, x0) + v[:, 0]), label="filter"))
    return ocp


def _mark_row_groups(ocp: OCP, keep: np.ndarray, N: int) -> None:
    """Record which rows of (4.5c) belong together, as metadata of ``ocp`` for a backend that
    generates rows (:mod:`balustrade.backends.row_generation`): the rows of stage ``i`` and
    facet ``r`` of 𝕏₀, one per vertex of ``Θ_k`` (those kept by ``keep``), form group
    ``i · n_X + r``. ``ocp.row_groups`` maps each block ``tube_vertex_j`` to the group of each
    of its rows (the block's row order: stages, then the kept facets); ``ocp.row_group_stride``
    is ``n_X``, the groups per stage (group ``g + n_X`` is group ``g`` one stage later)."""
    n_x = keep.shape[0]
    groups = {}
    for j in range(keep.shape[1]):
        r_j = np.flatnonzero(keep[:, j])
        if r_j.size:
            groups[f"tube_vertex_{j}"] = (np.arange(N)[:, None] * n_x + r_j[None, :]).ravel()
    ocp.row_groups = groups
    ocp.row_group_stride = n_x


def _checked_shared(shared: object, shape: tuple[int, int], name: str) -> np.ndarray:
    """``shared`` of :func:`rapsf_problem` as an integer array of ``shape`` (``n_X × n_θ``)
    whose entries name a representative that is not later than the vertex and is its own
    representative (``0 <= shared[r, j] <= j``, ``shared[r, shared[r, j]] == shared[r, j]``),
    as :func:`shared_rows` returns; anything else would silently drop rows of (4.5c), so it
    is a :class:`BalustradeError` naming the first offending ``(r, j)`` and the shape."""
    arr = np.asarray(shared)
    if arr.shape != shape:
        raise ShapeError(f"{name}: shared", shape, arr.shape)
    if arr.dtype.kind not in "iu":
        flt = as_float_array(arr, f"{name}: shared")
        if not np.all(np.isfinite(flt)) or np.any(flt != np.round(flt)):
            raise BalustradeError(f"{name}: shared (shape {arr.shape}) must hold integer "
                                  f"vertex indices, got dtype {arr.dtype}")
    rep = arr.astype(np.int64)
    cols = np.arange(shape[1])[None, :]
    bad = (rep < 0) | (rep > cols)
    if not np.any(bad):
        bad = np.take_along_axis(rep, rep, axis=1) != rep
    if np.any(bad):
        r, j = (int(i) for i in np.argwhere(bad)[0])
        raise BalustradeError(f"{name}: shared (shape {arr.shape}) at (r, j) = ({r}, {j}) is "
                              f"{rep[r, j]}: each entry must be a vertex index "
                              f"0 <= shared[r, j] <= j whose own entry is itself "
                              f"(shared[r, shared[r, j]] == shared[r, j], as shared_rows "
                              "returns); else rows of (4.5c) would be dropped")
    return rep


def _theta_parts(system: object, K: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """``[A_cl,0, B_0]`` and ``M_k = [A_k + B_k K, B_k]`` (``n × (n + m)``, acting on
    ``(z_i, v_i)``): ``[A_cl(θ), B(θ)] = [A_cl,0, B_0] + Σ_k θ_k M_k``."""
    A0, B0 = (np.asarray(M, dtype=float) for M in (system.A0, system.B0))
    M0 = np.hstack([A0 + B0 @ K, B0])
    Ms = [np.hstack([np.asarray(Ak, dtype=float) + np.asarray(Bk, dtype=float) @ K,
                     np.asarray(Bk, dtype=float)])
          for Ak, Bk in zip(system.A_list, system.B_list, strict=True)]
    return M0, Ms


def factored_pays(system: object, X0: Polytope, K: np.ndarray, keep: np.ndarray) -> bool:
    """Whether the factored rows of :func:`rapsf_problem` (``factored=True``), with the rows
    defining ``y``, have at most half the nonzeros of the plain rows of (4.5c) (``keep``: the
    rows built per vertex). The factored form adds ``n_X N`` variables and equalities, so a
    small saving does not pay: measured on ``"fast-convex"``, 3 masses (332 vs 366 nonzeros
    per stage) solve 14–60 % slower factored; 8 masses (31468 vs 102848) 5× faster."""
    HX = unit_polytope(X0, "factored_pays")
    M0, Ms = _theta_parts(system, K)
    Mth = sum((np.abs(M) for M in Ms), np.zeros_like(M0)) != 0
    Hn = HX != 0
    n = HX.shape[1]
    plain = np.count_nonzero(Hn.astype(float) @ ((np.abs(M0) != 0) | Mth), axis=1) \
        + np.count_nonzero(Hn, axis=1) + 2
    theta_cols = np.count_nonzero(sum((np.abs(HX @ M) for M in Ms),
                                      np.zeros((HX.shape[0], M0.shape[1]))) != 0, axis=1)
    fact = 3 + theta_cols
    define = np.count_nonzero(Hn.astype(float) @ (np.abs(M0) != 0), axis=1) \
        + np.count_nonzero(Hn[:, :n], axis=1) + 1
    counts = np.count_nonzero(keep, axis=1)
    return bool(2 * (np.sum(counts * fact) + np.sum(define)) <= np.sum(counts * plain))


def _tube_rows_factored(ocp: OCP, system: object, HX: np.ndarray, K: np.ndarray,
                        thetas: list, s: object, w_bar: np.ndarray, keep: np.ndarray,
                        z: ca.SX, alpha: ca.SX, v: ca.SX, N: int, z_next: ca.SX,
                        a_next: ca.SX) -> None:
    """(4.5c) in the factored form of :func:`rapsf_problem` (``factored=True``);
    ``z_next``, ``a_next`` are ``z[:, 1:]``, ``alpha[1:]`` or their stage copies."""
    M0, Ms = _theta_parts(system, K)
    HM = [HX @ M for M in Ms]                                  # [H_X]_r M_k, per k
    used = np.flatnonzero(np.any([M != 0 for M in HM], axis=(0, 1))) if HM \
        else np.zeros(0, dtype=int)
    cols = used.tolist()
    n_x = HX.shape[0]
    y = ocp.variable("tube_offset", n_x, N)
    H0 = ca.DM(HX @ M0)
    w = [ca.vertcat(z[:, i], v[:, i]) for i in range(N)]
    ocp.eq(ca.vertcat(*[y[:, i] - (ca.mtimes(H0, w[i]) - ca.mtimes(ca.DM(HX), z_next[:, i]))
                        for i in range(N)]), 0.0, name="tube_offset", tag="tube")
    for j, th in enumerate(thetas):
        r_j = np.flatnonzero(keep[:, j]).tolist()
        if not r_j:
            continue
        coef = ca.DM.zeros(len(r_j), len(cols))
        for k, HMk in enumerate(HM):
            block = HMk[np.ix_(r_j, cols)]
            if np.any(block != 0):
                coef = coef + th[k] * ca.DM(block)
        one_j, wb_j = ca.DM.ones(len(r_j), 1), ca.DM(w_bar[r_j])
        rows = [y[r_j, i] + (ca.mtimes(coef, w[i][cols]) if cols else 0)
                + alpha[i] * s[r_j, j] + wb_j - a_next[i] * one_j for i in range(N)]
        ocp.le(ca.vertcat(*rows), name=f"tube_vertex_{j}", tag="tube")


def _staged_variables(system: object, n: int, m: int, N: int, name: str) -> tuple:
    """The variables of (4.5) in stage order (``rapsf_problem(staged=True)``): the state of
    stage ``i`` is ``(z_i, α_i)``, its controls ``(v_i, ẑ_{i+1}, α̂_{i+1})`` with the
    dynamics ``z_{i+1} = ẑ_{i+1}``, ``α_{i+1} = α̂_{i+1}`` (tag ``dynamics``). Every row of
    (4.5c) then reads ``(z_i, α_i, v_i, ẑ_{i+1}, α̂_{i+1})`` only — a general constraint of
    stage ``i`` — so the problem has the stage structure of the stage-order pass
    (:mod:`balustrade.backends.passes.stage_order`, the structured targets) with the
    same feasible set and optimum as the plain form. The OCP's system is the nominal model
    (only a horizon OCP is stage-ordered; its own dynamics ``f`` are not used)."""
    nominal = LinearSystem(np.asarray(system.A0, dtype=float),
                           np.asarray(system.B0, dtype=float), name=f"{name}_nominal")
    ocp = OCP(nominal, N, name=name, state_name="z", input_name="v")
    z, v = ocp.x, ocp.u
    alpha = ocp.variable("alpha", 1, N + 1, lb=0.0, role="state")
    z_next = ocp.variable("z_next", n, N, role="input")
    a_next = ocp.variable("alpha_next", 1, N, role="input")
    ocp.eq(ca.horzcat(*[ca.vertcat(z[:, i + 1] - z_next[:, i], alpha[i + 1] - a_next[i])
                        for i in range(N)]), 0.0, name="stage_copies", tag="dynamics")
    return ocp, z, alpha, v, z_next, a_next


def _symbolic_models(system: object, thetas: Sequence[ca.SX | ca.DM]
                     ) -> tuple[list, list]:
    A0, B0 = ca.DM(np.asarray(system.A0, float)), ca.DM(np.asarray(system.B0, float))
    As = [ca.DM(np.asarray(a, float)) for a in system.A_list]
    Bs = [ca.DM(np.asarray(b, float)) for b in system.B_list]
    A_out, B_out = [], []
    for th in thetas:
        A, B = A0, B0
        for k, (Ak, Bk) in enumerate(zip(As, Bs, strict=True)):
            A = A + th[k] * Ak
            B = B + th[k] * Bk
        A_out.append(A)
        B_out.append(B)
    return A_out, B_out


def _terminal(ocp: OCP, zN: ca.SX, aN: ca.SX, terminal: TerminalSet | None, n: int,
              name: str) -> None:
    if terminal is not None and terminal.has_generators:
        _terminal_hull(ocp, zN, aN, terminal, n, name)
        return
    if terminal is None or terminal.H_T is None:
        ocp.eq(zN, 0.0, name="terminal_center", tag="terminal")
        ocp.le(aN, 1.0, name="terminal_dilation", tag="terminal")
        return
    H_T, h_T = _terminal_rows(terminal, n, name)
    ocp.le(ca.mtimes(ca.DM(H_T), zN) + ca.DM(h_T) * aN, 1.0, name="terminal", tag="terminal")


def _terminal_rows(terminal: TerminalSet, n: int, name: str) -> tuple[np.ndarray, np.ndarray]:
    H_T = as_matrix(terminal.H_T, f"{name}: terminal H_T", (None, n))
    h_T = as_vector(terminal.h_T, f"{name}: terminal h_T", H_T.shape[0])
    return H_T, h_T


def check_terminal(terminal: object, n: int, name: str) -> None:
    """The terminal set (4.5e) of a controller, checked when it is built rather than at the
    first solve: a :class:`TerminalSet` whose ``H_T`` has ``n`` columns and whose ``H_T``,
    ``h_T`` (one entry per row) and numeric generators (``n + 1`` rows) are finite; else a
    :class:`~balustrade.errors.BalustradeError` naming the field and the shapes."""
    if terminal is None:
        return
    check_instance(terminal, TerminalSet, f"{name}: terminal")
    if terminal.H_T is not None or terminal.h_T is not None:
        if terminal.H_T is None or terminal.h_T is None:
            raise BalustradeError(f"{name}: terminal needs both H_T and h_T (or neither: "
                                  "the default z_N = 0, 0 <= α_N <= 1)")
        _terminal_rows(terminal, n, name)
    if terminal.Z is not None:
        as_matrix(terminal.generators, f"{name}: terminal generators [Z; a]", (n + 1, None))


def _terminal_hull(ocp: OCP, zN: ca.SX, aN: ca.SX, terminal: TerminalSet, n: int,
                   name: str) -> None:
    """(4.5e) with the hull of generators and the base set, perspective form of SPEC §2.22."""
    if terminal.capacity is not None:
        gens = ocp.parameter("terminal_generators", n + 1, terminal.capacity)
        count = terminal.capacity
    else:
        V = terminal.generators
        if V.shape[0] != n + 1:
            raise ShapeError(f"{name}: terminal generators Z", f"{n} rows (the state "
                             "dimension)", (V.shape[0] - 1, V.shape[1]))
        gens, count = ca.DM(V), V.shape[1]
    lam = ocp.variable("terminal_lambda", count, 1, lb=0.0)
    lam_f = ocp.variable("terminal_lambda_base", 1, 1, lb=0.0)
    a_b = ocp.variable("terminal_alpha_base", 1, 1, lb=0.0)
    if terminal.H_T is None:                                  # λ_f·{z = 0, 0 <= α <= 1}
        z_b = ca.DM.zeros(n, 1)
        ocp.le(a_b - lam_f, 0.0, name="terminal_base", tag="terminal")
    else:                                                     # λ_f·{H_T z + h_T α <= 1}
        H_T, h_T = _terminal_rows(terminal, n, name)
        z_b = ocp.variable("terminal_z_base", n, 1)
        ocp.le(ca.mtimes(ca.DM(H_T), z_b) + ca.DM(h_T) * a_b - lam_f, 0.0,
               name="terminal_base", tag="terminal")
    hull = ca.mtimes(gens, lam) + ca.vertcat(z_b, a_b)
    ocp.eq(ca.vertcat(zN, aN) - hull, 0.0, name="terminal_hull", tag="terminal")
    ocp.eq(ca.sum1(lam) + lam_f, 1.0, name="terminal_weights", tag="terminal")


# -- the robust gain LMI ----------------------------------------------------------------------
def robust_gain_sdp(system: object, vertices: np.ndarray, contraction: float = 0.95
                    ) -> SynthesisProblem:
    """Quadratic stabilization of ``A(θ^j) + B(θ^j)K`` at every vertex of ``Θ₀`` with decay
    ``λ = contraction``: ``[[λ² E, (A_jE + B_jY)ᵀ], [A_jE + B_jY, E]] ⪰ 0``, ``E ⪰ I``,
    ``min tr E``; ``K = Y E⁻¹`` (variables ``E``, ``Y``)."""
    n, m, _ = check_parametric_system(system, "robust_gain_sdp")
    if not 0 < contraction <= 1:
        raise BalustradeError(f"robust_gain_sdp: contraction must lie in (0, 1], got "
                              f"{contraction}")
    sdp = SynthesisProblem("robust gain LMI (SPEC §2.20 [Default])")
    E = sdp.matrix("E", (n, n), symmetric=True)
    Y = sdp.matrix("Y", (m, n))
    sdp.lmi("E >= I", E >> np.eye(n))
    for j, th in enumerate(np.atleast_2d(vertices)):
        A, B = model_matrices(system, th)
        AEBY = A @ E + B @ Y
        sdp.lmi(f"vertex {j}", bmat([[contraction ** 2 * E, AEBY.T], [AEBY, E]]))
    sdp.minimize(trace(E))
    return sdp


__all__ = ["TerminalSet", "TubeConstants", "check_parametric_system", "check_terminal",
           "check_tube_sets", "check_vertices", "closed_loop_matrices", "disturbance_map",
           "factored_pays", "joint_constraints", "model_matrices", "parameter_vertices",
           "rapsf_problem", "robust_gain_sdp", "row_dependence", "rows_shared",
           "s_constants", "shared_rows", "support_rows", "tube_constants", "unit_polytope"]
