"""Multiobjective formulations of thesis Chapter 6.

* :class:`LinearLyapunovDesign` — the linear design of Section 6.3.2: ``l = ½xᵀQx + ½uᵀRu``,
  ``m = ½xᵀPx`` with ``P`` from (6.13) (SPEC [Default]: ``A_Kᵀ P A_K − P = −(Q + KᵀRK)``), the
  implicit Lyapunov function ``V((x, u))`` (6.2), the warm-start generators ``ξ_c`` (6.11) and
  ``ξ_f`` (6.12) and the switching rule (6.6)/(6.7);
* :func:`multiobjective_lyapunov_problem` — (6.3) in the linear form (6.10): reachable-set
  tightenings and the Lyapunov decrease (6.3h) against the parameter ``bound``
  ``= V((x_k, ũ_k)) − (1 − ρ) l(x_k, ũ_0)`` (computed by the algorithm, keeping the parameter
  affine);
* :func:`multiobjective_pcbf_problem` — (6.15): the robust PCBF constraints (5.15b–f) with the
  slack decrease (6.15g) ``α_f ξ_N + Σ_i ‖ξ_i‖ <= bound``, ``bound = (1−ρ) h̃(ξ̃_k) + ρ h̃(ξ*_{k−1})``.
  The slack norm is ``ℓ1``: with ``ξ_i >= 0`` it is ``1ᵀξ_i``, a linear constraint on both
  backends (an ``ℓ2`` norm inside a constraint would need epigraph cones; SPEC §3.4's default for
  the rendezvous is ``ℓ1``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import casadi as ca
import numpy as np
import scipy.linalg

from balustrade._checks import (
    as_matrix,
    as_scalar,
    check_callable,
    check_horizon,
    check_instance,
    check_weight,
)
from balustrade.dsl import OCP, LinearSystem, Polytope, System, squared_norm
from balustrade.dsl.error_sets import ErrorSet, reachable_tightened_sets
from balustrade.errors import BalustradeError
from balustrade.problems._args import (
    check_pcbf_args,
    check_system_sets,
    positive,
)
from balustrade.problems._costs import stage_cost, trajectory_cost
from balustrade.problems.robust import Objective, _syms, _tube_blocks, robust_sets


# -- linear design (6.9)–(6.13) ----------------------------------------------------------------
def terminal_weight(A: np.ndarray, B: np.ndarray, K: np.ndarray, Q: np.ndarray, R: np.ndarray,
                    printed: bool = False) -> np.ndarray:
    """``P`` of (6.13): ``A_Kᵀ P A_K − P = −(Q + KᵀRK)`` (SPEC [Default]); ``printed=True``
    solves the thesis' printed ``A_Kᵀ P A_K − P = −Q`` (violates Assumption 6.7.5 if ``K ≠ 0``)."""
    A = as_matrix(A, "terminal_weight: A")
    n = A.shape[0]
    if A.shape != (n, n):
        raise BalustradeError(f"terminal_weight: A must be square, got shape {A.shape}")
    B = as_matrix(B, "terminal_weight: B", (n, None))
    K = as_matrix(K, "terminal_weight: K", (B.shape[1], n))
    Q = check_weight(Q, n, "terminal_weight: Q")
    R = check_weight(R, B.shape[1], "terminal_weight: R")
    A_K = A + B @ K
    if np.max(np.abs(np.linalg.eigvals(A_K))) >= 1:
        raise BalustradeError("terminal_weight: A + BK is not Schur stable; the Lyapunov "
                              "equation (6.13) has no PSD solution")
    rhs = Q if printed else Q + K.T @ R @ K
    P = scipy.linalg.solve_discrete_lyapunov(A_K.T, rhs)
    return 0.5 * (P + P.T)


@dataclass
class LinearLyapunovDesign:
    """Data of (6.10): ``x⁺ = Ax + Bu + w``, ``w ∈ W``, feedback ``K``, weights ``Q, R, P``, the
    tightened sets ``X ⊖ E_i``, ``U ⊖ K E_i`` (``i ∈ I[0, N]``) and ``X_f ⊖ E_N``."""

    system: LinearSystem
    X: Polytope
    U: Polytope
    Xf: Polytope
    W: Polytope
    K: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    N: int
    P: np.ndarray | None = None

    def __post_init__(self) -> None:
        check_instance(self.system, LinearSystem, "LinearLyapunovDesign: system")
        check_system_sets("LinearLyapunovDesign", self.system, self.X, self.U, polytope=True,
                          Xf=self.Xf)
        check_instance(self.W, Polytope, "LinearLyapunovDesign: W")
        self.N = check_horizon(self.N, "LinearLyapunovDesign")
        A, B = self.system.A, self.system.B
        n, m = A.shape[0], B.shape[1]
        self.Q = check_weight(self.Q, n, "LinearLyapunovDesign: Q")
        self.R = check_weight(self.R, m, "LinearLyapunovDesign: R")
        if self.P is not None:
            self.P = check_weight(self.P, n, "LinearLyapunovDesign: P")
        self.K = as_matrix(self.K, "LinearLyapunovDesign: K", (B.shape[1], A.shape[0]))
        self.A_K = A + B @ self.K
        if np.max(np.abs(np.linalg.eigvals(self.A_K))) >= 1:
            raise BalustradeError("LinearLyapunovDesign: A + BK is not Schur stable")
        if self.P is None:
            self.P = terminal_weight(A, B, self.K, self.Q, self.R)
        G = self.system.E if self.system.nw else None
        self.G = np.eye(A.shape[0]) if G is None else G
        self.Xs = reachable_tightened_sets(self.X, self.A_K, self.W, self.N, self.G, name="X")
        self.Us = reachable_tightened_sets(self.U, self.A_K, self.W, self.N, self.G, K=self.K,
                                           name="U")
        self.Xf_N = reachable_tightened_sets(self.Xf, self.A_K, self.W, self.N, self.G,
                                             name="Xf")[self.N]

    # costs and V (6.2)
    def stage(self, x: np.ndarray, u: np.ndarray) -> float:
        """``l(x, u) = ½xᵀQx + ½uᵀRu``."""
        return 0.5 * stage_cost(x, u, self.Q, self.R)

    def m(self, x: np.ndarray) -> float:
        return float(0.5 * x @ self.P @ x)

    def rollout(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """``φ(x, u; i)`` for ``i ∈ I[0, len(u)]`` as columns (nominal model)."""
        A, B = self.system.A, self.system.B
        u = np.asarray(u, dtype=float).reshape(B.shape[1], -1)
        z = [np.asarray(x, dtype=float).reshape(-1)]
        for i in range(u.shape[1]):
            z.append(A @ z[-1] + B @ u[:, i])
        return np.column_stack(z)

    def V(self, x: np.ndarray, u: np.ndarray) -> float:
        """(6.2): ``Σ_i l(φ_i, u_i) + m(φ_N)``."""
        u = np.asarray(u, dtype=float).reshape(self.system.nu, -1)
        return 0.5 * trajectory_cost(self.rollout(x, u), u, self.Q, self.R, self.P)

    # warm-start generators
    def xi_c(self, x_next: np.ndarray, v: np.ndarray, w: np.ndarray) -> np.ndarray:
        """(6.11) with the SPEC corrections: ``(v_1 + Kw, …, v_{N−1} + K A_K^{N−2} w, last)``,
        ``last = K φ(x_next, (ũ_0, …, ũ_{N−2}); N−1)`` (equal to ``K z_N + K A_K^{N−1} w``).
        ``w`` is the disturbance in state coordinates, ``x_{k+1} − A x_k − B u_k``."""
        v = np.asarray(v, dtype=float).reshape(self.system.nu, -1)
        w = np.asarray(w, dtype=float).reshape(-1)
        N = v.shape[1]
        out = np.zeros_like(v)
        e = w
        for i in range(N - 1):
            out[:, i] = v[:, i + 1] + self.K @ e
            e = self.A_K @ e
        z = self.rollout(x_next, out[:, : N - 1])
        out[:, N - 1] = self.K @ z[:, -1]
        return out

    def xi_f(self, x: np.ndarray) -> np.ndarray:
        """(6.12): ``(Kx, K A_K x, …, K A_K^{N−1} x)``."""
        cols, z = [], np.asarray(x, dtype=float).reshape(-1)
        for _ in range(self.N):
            cols.append(self.K @ z)
            z = self.A_K @ z
        return np.column_stack(cols)

    def admissible(self, x: np.ndarray, u: np.ndarray, tol: float = 1e-9) -> bool:
        """Whether ``u`` and its rollout from ``x`` satisfy (6.3b–g)."""
        u = np.asarray(u, dtype=float).reshape(self.system.nu, -1)
        z = self.rollout(x, u)
        return (all(self.Xs[i].contains(z[:, i], tol) for i in range(self.N))
                and all(self.Us[i].contains(u[:, i], tol) for i in range(self.N))
                and self.Xf_N.contains(z[:, -1], tol))

    def switch(self, x: np.ndarray, v: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, str]:
        """Switching rule (6.6)/(6.7): ``ξ_f`` if ``x ∈ X_f``, it does not increase ``V`` over
        ``ξ_c`` and (SPEC [Default]) its rollout satisfies (6.3b–g); else ``ξ_c``."""
        cand_c = self.xi_c(x, v, w)
        if self.Xf.contains(x, 1e-12):
            cand_f = self.xi_f(x)
            if self.V(x, cand_f) <= self.V(x, cand_c) and self.admissible(x, cand_f):
                return cand_f, "xi_f"
        return cand_c, "xi_c"

    def bound(self, x: np.ndarray, u_tilde: np.ndarray, rho: float) -> float:
        """Right side of (6.3h): ``V((x, ũ)) − (1 − ρ) l(x, ũ_0)``."""
        u_tilde = np.asarray(u_tilde, dtype=float).reshape(self.system.nu, -1)
        return self.V(x, u_tilde) - (1.0 - rho) * self.stage(x, u_tilde[:, 0])


def multiobjective_lyapunov_problem(design: LinearLyapunovDesign, decrease: bool = True,
                                    objective: Objective | None = None,
                                    name: str = "multiobjective_lyapunov") -> OCP:
    """(6.10): ``min J`` s.t. ``z_0 = x_k``, ``z_{i+1} = Az_i + Bv_i``, ``z_i ∈ X ⊖ E_i``,
    ``v_i ∈ U ⊖ K E_i``, ``z_N ∈ X_f ⊖ E_N`` and (6.3h) at ``z_1 = Ax_k + Bv_0``:
    ``Σ_{i=1}^{N−1} l(z_i, v_i) + l(z_N, Kz_N) + m(A_K z_N) <= bound``
    (``V((z_1, ξ_c(z_1, v, 0)))``, a convex quadratic). Parameters ``x0``, ``u_p``, ``bound``.
    ``decrease=False`` drops (6.3h): the feasibility problem of Algorithm 6.3 step 2 (cost
    ``‖v‖²``). Default ``J = ‖v_0 − u_p‖²``."""
    check_instance(design, LinearLyapunovDesign, f"{name}: design")
    if objective is not None:
        check_callable(objective, f"{name}: objective")
    d, N = design, design.N
    ocp = OCP(d.system, N, name=name, state_name="z", input_name="v")
    x0 = ocp.parameter("x0", d.system.nx)
    u_p = ocp.parameter("u_p", d.system.nu)
    ocp.initial_state(x0)
    ocp.dynamics()
    ocp.state_constraint(d.Xs[:N])
    ocp.input_constraint(d.Us[:N])
    ocp.terminal_constraint(d.Xf_N)
    z, v = ocp.x, ocp.u
    if decrease:
        bound = ocp.parameter("bound", 1)
        zN = z[:, N]
        # V((z_1, ξ_c(z_1, v, 0))) = ½ [Σ_{i=1}^{N−1} l(z_i, v_i) + l(z_N, Kz_N)] + m(A_K z_N)
        states = ca.horzcat(z[:, 1:N + 1], ca.mtimes(ca.DM(d.A_K), zN))
        inputs = ca.horzcat(v[:, 1:N], ca.mtimes(ca.DM(d.K), zN))
        lhs = 0.5 * trajectory_cost(states, inputs, d.Q, d.R, d.P)
        ocp.decrease(lhs, bound, name="lyapunov_decrease")                    # (6.3h)
        syms = {"x0": x0, "u_p": u_p, "z": z, "v": v, "u0": v[:, 0]}
        ocp.minimize(objective(ocp, syms) if objective is not None
                     else squared_norm(v[:, 0] - u_p, label="filter"))
    else:
        ocp.minimize(squared_norm(ca.vec(v), label="feasibility"))
    return ocp


# -- multiobjective robust PCBF (6.15) -----------------------------------------------------------
def multiobjective_pcbf_problem(system: System, X: Polytope, U: Polytope, h_f: Callable,
                                N: int, deltas: np.ndarray, error: ErrorSet,
                                alpha_f: float = 1e6, objective: Objective | None = None,
                                U_tight: Polytope | None = None,
                                name: str = "multiobjective_pcbf",
                                running_sum: bool = False) -> OCP:
    """(6.15): ``min J`` over ``z`` (with ``z_0``), ``v``, ``ξ`` s.t. (6.15b–f) = (5.15b–f) and
    (6.15g) ``α_f ξ_N + Σ_i 1ᵀξ_i <= bound`` (ℓ1 slack norm, linear since ``ξ >= 0``).

    Parameters ``x0``, ``u_p``, ``bound`` (``= (1−ρ) h̃(ξ̃_k) + ρ h̃(ξ*_{k−1})``). Variables ``z``,
    ``v``, ``xi``, ``xi_N``. Default ``J = ‖u_p − (v_0 + K(x_k − z_0))‖²``.

    ``running_sum=True`` writes (6.15g) stage by stage (:func:`_running_sum_decrease`): the
    same feasible set and minimizers (``z``, ``v``, ``ξ``, ``ξ_N``), one more variable
    ``xi_sum`` (``σ_i = Σ_{j<=i} 1ᵀξ_j``, ``N`` entries, fixed by ``z, v, ξ``) and ``N``
    equality rows, but no row that touches every slack.
    """
    N, deltas = check_pcbf_args(name, system, X, U, h_f, N, deltas, polytope=True)
    alpha_f = positive(alpha_f, f"{name}: alpha_f")
    if objective is not None:
        check_callable(objective, f"{name}: objective")
    sets = robust_sets(X, U, error, U_tight)
    ocp = OCP(system, N, name=name, state_name="z", input_name="v")
    x0 = _tube_blocks(ocp, system, sets, error)                      # (6.15b–d)
    u_p = ocp.parameter("u_p", system.nu)
    bound = ocp.parameter("bound", 1)
    xi = ocp.variable("xi", sets.X_E.n_rows, N, lb=0.0, role="slack")
    xi_N = ocp.variable("xi_N", 1, 1, lb=0.0, role="slack")
    ocp.state_constraint(sets.X_E, tightening=deltas, slack=xi)      # (6.15e)
    ocp.terminal_cbf(h_f, slack=xi_N)                                # (6.15f)
    if running_sum:
        _running_sum_decrease(ocp, xi, xi_N, alpha_f, bound)                  # (6.15g)
    else:
        ocp.decrease(alpha_f * xi_N + ca.sum1(ca.sum2(xi)), bound,
                     name="slack_decrease")                                   # (6.15g)
    syms = _syms(ocp, x0, u_p, error)
    ocp.minimize(objective(ocp, syms) if objective is not None
                 else squared_norm(syms["u0"] - u_p, label="filter"))
    return ocp


def _running_sum_decrease(ocp: OCP, xi: ca.SX, xi_N: ca.SX, alpha_f: float,
                          bound: ca.SX) -> None:
    """(6.15g) through the running sums ``σ_0 = 1ᵀξ_0``, ``σ_i = σ_{i−1} + 1ᵀξ_i``
    (``i ∈ I[1, N−1]``, block ``slack_running_sum``) and ``α_f ξ_N + σ_{N−1} <= bound``
    (block ``slack_decrease``): equivalent to the single row, since the equalities fix
    ``σ``.

    Why: the single row has a nonzero for every slack (``n_X N + 1`` of them). In the KKT
    matrix that the SQP's QP solver of the ``robust-sqp`` target factorizes by sparse QR at
    each of its iterations, that row couples every stage and fills the factor in. On the
    lane change (§8.2, ``N = 20``, 285 variables) a (6.15) solve took a median of 36 ms with
    the single row and 1.9 ms with the running sums (under load, 22 closed-loop states of
    seed 0, the same SQP iterations, inputs equal to 5e-9; ``benchmarks/bench_lane.py``
    measures the whole step). Each running-sum row touches one stage. Not the default: on
    the 2-D example of §5.6 the SQP alone converged from the candidate at ``k = 0`` on 5 of
    49 far-off random states with it against 40 without (``h̃`` up to 1e8 there)."""
    N = xi.shape[1]
    sigma = ocp.variable("xi_sum", 1, N)
    prev = ca.vertcat(ca.SX(0), sigma[0, : N - 1].T) if N > 1 else ca.SX(0)
    ocp.eq(sigma.T - prev - ca.sum1(xi).T, 0.0, name="slack_running_sum")
    ocp.decrease(alpha_f * xi_N + sigma[0, N - 1], bound, name="slack_decrease")


def decrease_bound(h_tilde_candidate: float, h_tilde_previous: float, rho: float) -> float:
    """Right side of (6.15g): ``(1 − ρ) h̃(ξ̃_k) + ρ h̃(ξ*_{k−1})`` for ``ρ ∈ [0, 1)``."""
    rho = as_scalar(rho, "(6.15g): ρ", low=0.0, high=1.0, high_open=True)
    h_tilde_candidate = as_scalar(h_tilde_candidate, "(6.15g): h̃(ξ̃_k)")
    h_tilde_previous = as_scalar(h_tilde_previous, "(6.15g): h̃(ξ*_{k−1})")
    return (1.0 - rho) * h_tilde_candidate + rho * h_tilde_previous
