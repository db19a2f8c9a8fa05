"""The baseline of thesis §4.7 (Table 4.1, Fig. 4.2): the robust predictive safety filter of
[31] with the parametric uncertainty folded into an enlarged disturbance set and no
adaptation (SPEC §3.2 [Default]).

The prediction model is the nominal ``A(θ_c)``, ``B(θ_c)`` at the centre ``θ_c`` of ``Θ₀``;
the true successor is ``x⁺ = A(θ_c)x + B(θ_c)u + w̃`` with

    ``w̃ = w + (A(θ) − A(θ_c))x + (B(θ) − B(θ_c))u  ∈  W̃ = W ⊕ {… : θ ∈ Θ₀, x ∈ X, u ∈ U}``,

valid as long as ``(x, u) ∈ X × U`` — which the filter's constraints keep. :func:`enlarged_
disturbance` returns a box outer bound of ``W̃`` (:func:`enlarged_disturbance`; exact for a box
``W`` and springs acting on disjoint coordinates per row, as in the mass–spring–damper chain).

**Tube parametrisation.** To isolate what adaptation buys, the baseline uses the same
homothetic tubes ``{z_i} ⊕ α_i 𝕏₀`` with feedback ``Kx + v`` and the same terminal set
``z_N = 0, 0 <= α_N <= 1`` as (4.5) (SPEC §2.20), with one vertex ``θ_c`` and ``W̃`` instead of
the vertices of ``Θ_k`` and ``W``: :func:`baseline_psf_problem` is
:func:`~balustrade.problems.rapsf.rapsf_problem` on those data. [31] tightens with the
reachable sets of the error instead (a rigid tube, ``α_i = 1``), which is one feasible point of
this program when ``𝕏₀`` is robustly invariant for ``W̃``, so this baseline is at least as
permissive as [31]'s with the same ``𝕏₀``.
"""

from __future__ import annotations

import numpy as np

from balustrade._checks import check_instance
from balustrade.dsl import OCP, Polytope
from balustrade.dsl.joint import JointPolytope, as_joint
from balustrade.dsl.sets import Box
from balustrade.errors import BalustradeError, ShapeError
from balustrade.problems.rapsf import (
    TerminalSet,
    check_parametric_system,
    disturbance_map,
    rapsf_problem,
)


def nominal_parameter(Theta0: Polytope) -> np.ndarray:
    """``θ_c``: the centre of the box ``Θ₀``."""
    return 0.5 * (_box(Theta0, "nominal_parameter: Theta0").lb + Theta0.ub)


def _box(S: Polytope, where: str) -> Box:
    check_instance(S, Polytope, where)
    if not isinstance(S, Box) or not S.is_bounded():
        raise BalustradeError(f"{where} must be a bounded Box, got {type(S).__name__}")
    return S


def _abs_max(M: np.ndarray, S: Box) -> np.ndarray:
    """``max_{s∈S} |M_r s|`` for every row ``r`` (``|M_r c| + |M_r| h`` for centre ``c``, half
    width ``h``)."""
    c, h = 0.5 * (S.lb + S.ub), 0.5 * (S.ub - S.lb)
    return np.abs(M @ c) + np.abs(M) @ h


def enlarged_disturbance(system: object, Theta0: Box, W: Polytope, X: Box, U: Box,
                         name: str = "W_enlarged") -> Box:
    """A box containing ``W̃ = E W ⊕ {(A(θ) − A(θ_c))x + (B(θ) − B(θ_c))u : θ ∈ Θ₀,
    x ∈ X, u ∈ U}``: per state row ``r``, ``max_{w∈W} ±(Ew)_r`` plus
    ``Σ_j ρ_j (max_{x∈X} |(A_j x)_r| + max_{u∈U} |(B_j u)_r|)`` with ``ρ_j`` the half widths
    of ``Θ₀`` (the maximum of a sum bounded by the sum of maxima)."""
    n, m, q = check_parametric_system(system, "enlarged_disturbance")
    Theta0 = _box(Theta0, "enlarged_disturbance: Theta0")
    X, U = _box(X, "enlarged_disturbance: X"), _box(U, "enlarged_disturbance: U")
    check_instance(W, Polytope, "enlarged_disturbance: W")
    if Theta0.dim != q:
        raise ShapeError("enlarged_disturbance: Theta0", f"dimension q = {q}",
                         f"dimension {Theta0.dim}", what="")
    if X.dim != n or U.dim != m:
        raise ShapeError("enlarged_disturbance: X, U", f"dimensions {n}, {m}",
                         f"{X.dim}, {U.dim}", what="")
    E = disturbance_map(system, n)
    if W.dim != E.shape[1]:
        raise ShapeError("enlarged_disturbance: W", f"dimension {E.shape[1]}",
                         f"dimension {W.dim}", what="")
    hi = np.array([W.support(E[r]) for r in range(n)])
    lo = -np.array([W.support(-E[r]) for r in range(n)])
    rho = 0.5 * (Theta0.ub - Theta0.lb)
    extra = np.zeros(n)
    for j in range(q):
        extra += rho[j] * (_abs_max(np.asarray(system.A_list[j], float), X)
                           + _abs_max(np.asarray(system.B_list[j], float), U))
    return Box(lo - extra, hi + extra, name=name)


def baseline_psf_problem(system: object, Theta0: Box, W_enlarged: Polytope, X0: Polytope,
                         F: np.ndarray | JointPolytope, G: np.ndarray | None,
                         K: np.ndarray, N: int,
                         terminal: TerminalSet | None = None,
                         X0_vertices: np.ndarray | None = None,
                         name: str = "baseline_psf") -> OCP:
    """The robust PSF of [31] as used in §4.7: (4.5) with the single vertex ``θ_c`` of
    :func:`nominal_parameter` and the enlarged disturbance ``W̃`` (:func:`enlarged_
    disturbance`); the system's ``E`` is replaced by ``I`` since ``W̃`` already holds ``Ew``.
    The joint constraints ``𝒵`` are the :class:`~balustrade.dsl.joint.JointPolytope` ``F``
    (``G=None``) or the matrices ``F, G`` of ``F x + G u <= 1``, imposed on the tubes by the
    block :func:`~balustrade.dsl.joint.joint_constraint` as in (4.5d).
    Parameters ``x0``, ``u_p``; apply ``K x + v_0``."""
    n, m, _ = check_parametric_system(system, name)
    Z = as_joint(F, G, name).check_dims(n, m, name)
    check_instance(W_enlarged, Polytope, f"{name}: W_enlarged")
    if W_enlarged.dim != n:
        raise ShapeError(f"{name}: W_enlarged", f"dimension n = {n}",
                         f"dimension {W_enlarged.dim}", what="")
    theta_c = nominal_parameter(Theta0)
    nominal = _Nominal(system)
    return rapsf_problem(nominal, X0, Z, None, W_enlarged, K, N, vertices=theta_c[None, :],
                         terminal=terminal, X0_vertices=X0_vertices, name=name)


class _Nominal:
    """``system`` with ``E = I`` (``W̃`` is a set of full-state disturbances)."""

    def __init__(self, system: object):
        self.A0, self.A_list = system.A0, system.A_list
        self.B0, self.B_list = system.B0, system.B_list
        self.E = None


__all__ = ["baseline_psf_problem", "enlarged_disturbance", "nominal_parameter"]
