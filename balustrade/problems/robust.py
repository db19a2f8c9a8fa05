"""Robust predictive control formulations (thesis Sections 2.5 and 5.5).

* :func:`robust_mpc_problem` — (2.14): nominal prediction from ``z_0 = x_k`` with the reachable-set
  tightenings ``X ⊖ E_i``, ``U ⊖ K E_i``, ``X_f ⊖ E_N``;
* :func:`tube_mpc_problem` — (2.15): ``x_k ∈ z_0 ⊕ E`` with ``z_0`` a decision variable,
  ``X ⊖ E``, ``U ⊖ K E``, ``z_N ∈ X_f``; apply ``v*_0 + K(x_k − z*_0)``;
* :func:`robust_pcbf_slack_problem` — (5.15): ``h_r(x_k)``;
* :func:`robust_pcbf_filter_problem` — (5.16): the filter with the slacks of (5.15) fixed;
* :func:`robust_candidate` — the shifted candidate (5.17) (with the SPEC §2.23 corrections:
  ``ξ*_{i+1|k}`` in the shift and ``c_x^E`` in the (N−1)-th slack), also the warm start (6.14);
* :func:`slack_cost` — ``h̃(ξ) = α_f ξ_N + Σ_i ‖ξ_i‖`` (SPEC §1.12).

The robustly tightened constraint function is ``c_x^E(z) = A_x z − b_x + s_E`` (SPEC §1.4): the
builders pass ``X ⊖ E`` (a :class:`~balustrade.dsl.sets.Polytope`) to ``state_constraint``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import casadi as ca
import numpy as np

from balustrade._checks import as_matrix, as_scalar, check_callable, check_horizon, check_instance
from balustrade.dsl import OCP, Polytope, System, squared_norm, sum_norms
from balustrade.dsl.costs import Cost
from balustrade.dsl.error_sets import ErrorSet, reachable_tightened_sets, tighten
from balustrade.errors import BalustradeError
from balustrade.problems._args import (
    check_norm_order,
    check_pcbf_args,
    check_system_sets,
    check_weights,
    nonnegative,
    positive,
)

Objective = Callable[[OCP, dict], object]


# -- (2.14), (2.15) -------------------------------------------------------------------------
def robust_mpc_problem(system: System, X: Polytope, U: Polytope, Xf: Polytope, N: int,
                       A_K: np.ndarray, K: np.ndarray, W: Polytope, Q: np.ndarray,
                       R: np.ndarray, P: np.ndarray, G: np.ndarray | None = None,
                       name: str = "robust_mpc") -> OCP:
    """(2.14): ``min Σ l(z_i, v_i) + l_f(z_N)`` s.t. ``z_0 = x_k``, nominal dynamics,
    ``z_i ∈ X ⊖ E_i``, ``v_i ∈ U ⊖ K E_i``, ``z_N ∈ X_f ⊖ E_N`` with
    ``E_i = ⊕_{j<i} A_K^j G W`` (support-function tightenings). Parameter ``x0``."""
    check_system_sets(name, system, X, U, polytope=True, Xf=Xf)
    N = check_horizon(N, name)
    Q, R, P = check_weights(name, system.nx, system.nu, Q, R, P)
    A_K = as_matrix(A_K, f"{name}: A_K", (system.nx, system.nx))
    K = as_matrix(K, f"{name}: K", (system.nu, system.nx))
    Xs = reachable_tightened_sets(X, A_K, W, N, G, name="X")
    Us = reachable_tightened_sets(U, A_K, W, N, G, K=K, name="U")
    Xf_N = reachable_tightened_sets(Xf, A_K, W, N, G, name="Xf")[N]
    ocp = OCP(system, N, name=name, state_name="z", input_name="v")
    ocp.initial_state(ocp.parameter("x0", system.nx))
    ocp.dynamics()
    ocp.state_constraint(Xs[:N])
    ocp.input_constraint(Us[:N])
    ocp.terminal_constraint(Xf_N)
    ocp.minimize(_stage_cost(ocp, Q, R, P))
    return ocp


def tube_mpc_problem(system: System, X: Polytope, U: Polytope, Xf: Polytope, N: int,
                     error: ErrorSet, Q: np.ndarray, R: np.ndarray, P: np.ndarray,
                     name: str = "tube_mpc") -> OCP:
    """(2.15): ``x_k − z_0 ∈ E`` (``z_0`` free), nominal dynamics, ``z_i ∈ X ⊖ E``,
    ``v_i ∈ U ⊖ K E``, ``z_N ∈ X_f``; apply ``v*_0 + K(x_k − z*_0)``. Parameter ``x0``."""
    check_system_sets(name, system, X, U, polytope=True)
    check_system_sets(name, system, Xf=Xf)
    N = check_horizon(N, name)
    Q, R, P = check_weights(name, system.nx, system.nu, Q, R, P)
    check_instance(error, ErrorSet, f"{name}: error")
    ocp = OCP(system, N, name=name, state_name="z", input_name="v")
    ocp.initial_tube(ocp.parameter("x0", system.nx), error.E)
    ocp.dynamics()
    ocp.state_constraint(error.tighten_state(X))
    ocp.input_constraint(error.tighten_input(U))
    ocp.terminal_constraint(Xf)
    ocp.minimize(_stage_cost(ocp, Q, R, P))
    return ocp


def _stage_cost(ocp: OCP, Q: np.ndarray, R: np.ndarray, P: np.ndarray) -> ca.SX:
    z, v = ocp.x, ocp.u
    Qd, Rd, Pd = ca.DM(Q), ca.DM(R), ca.DM(P)
    cost = sum(ca.mtimes([z[:, i].T, Qd, z[:, i]]) + ca.mtimes([v[:, i].T, Rd, v[:, i]])
               for i in range(ocp.N))
    return cost + ca.mtimes([z[:, ocp.N].T, Pd, z[:, ocp.N]])


# -- robust PCBF (5.15), (5.16) -----------------------------------------------------------------
@dataclass(frozen=True)
class RobustSets:
    """``X ⊖ E`` and ``U ⊖ κ(E)`` used by (5.15)–(5.17), (6.15)."""

    X_E: Polytope
    U_E: Polytope


def robust_sets(X: Polytope, U: Polytope, error: ErrorSet,
                U_tight: Polytope | None = None) -> RobustSets:
    """``X ⊖ E`` and ``U ⊖ K E`` (or the user's ``U_tight`` for a nonlinear κ)."""
    check_instance(error, ErrorSet, "robust_sets: error")
    if U_tight is not None:
        check_instance(U_tight, Polytope, "robust_sets: U_tight")
    X_E = tighten(X, error.E, name=f"{X.name}⊖E")
    U_E = U_tight if U_tight is not None else error.tighten_input(U, name=f"{U.name}⊖KE")
    return RobustSets(X_E, U_E)


def _tube_blocks(ocp: OCP, system: System, sets: RobustSets, error: ErrorSet) -> ca.SX:
    x0 = ocp.parameter("x0", system.nx)
    ocp.initial_tube(x0, error.E)                       # (5.15b) x_k − z_0 ∈ E
    ocp.dynamics()                                      # (5.15c) z_{i+1} = f(z_i, v_i, 0)
    ocp.input_constraint(sets.U_E)                      # (5.15d) v_i ∈ U ⊖ κ(E)
    return x0


def robust_pcbf_slack_problem(system: System, X: Polytope, U: Polytope, h_f: Callable,
                              N: int, deltas: np.ndarray, error: ErrorSet,
                              alpha_f: float = 1e6, slack_norm: int | float = 1,
                              U_tight: Polytope | None = None,
                              name: str = "robust_pcbf_slack") -> OCP:
    """(5.15): ``h_r(x_k) = min α_f ξ_N + Σ_i ‖ξ_i‖`` s.t. (5.15b–f).

    Parameter ``x0``; variables ``z``, ``v``, ``xi`` (rows of ``c_x`` × N, ``>= 0``), ``xi_N``.
    """
    N, deltas = check_pcbf_args(name, system, X, U, h_f, N, deltas, polytope=True)
    alpha_f = positive(alpha_f, f"{name}: alpha_f")
    check_norm_order(slack_norm, f"{name}: slack_norm")
    sets = robust_sets(X, U, error, U_tight)
    ocp = OCP(system, N, name=name, state_name="z", input_name="v")
    _tube_blocks(ocp, system, sets, error)
    xi = ocp.variable("xi", sets.X_E.n_rows, N, lb=0.0, role="slack")
    xi_N = ocp.variable("xi_N", 1, 1, lb=0.0, role="slack")
    ocp.state_constraint(sets.X_E, tightening=deltas, slack=xi)    # (5.15e)
    ocp.terminal_cbf(h_f, slack=xi_N)                              # (5.15f)
    ocp.minimize(alpha_f * xi_N + sum_norms(xi, slack_norm, label="slack"))
    return ocp


def robust_pcbf_filter_problem(system: System, X: Polytope, U: Polytope, h_f: Callable,
                               N: int, deltas: np.ndarray, error: ErrorSet,
                               eps: float = 1e-6, objective: Objective | None = None,
                               U_tight: Polytope | None = None,
                               name: str = "robust_pcbf_filter") -> OCP:
    """(5.16): ``min J`` s.t. (5.16b–d) and the slacks fixed to the parameters ``xi``, ``xi_N``
    (the optimum of (5.15)) plus the margin ``eps``.

    Default ``J = ‖u_p − (v_0 + K(x_k − z_0))‖²`` (the safety-filter cost of (5.16) with the
    SPEC's parenthesization; squared: same minimizer, QP). ``objective(ocp, syms)`` may return
    any cost; ``syms`` holds ``x0``, ``u_p``, ``z``, ``v``, ``u0`` (the applied input expression).
    Parameters ``x0``, ``u_p``, ``xi``, ``xi_N``.
    """
    N, deltas = check_pcbf_args(name, system, X, U, h_f, N, deltas, polytope=True)
    eps = nonnegative(eps, f"{name}: eps")
    if objective is not None:
        check_callable(objective, f"{name}: objective")
    sets = robust_sets(X, U, error, U_tight)
    ocp = OCP(system, N, name=name, state_name="z", input_name="v")
    x0 = _tube_blocks(ocp, system, sets, error)
    u_p = ocp.parameter("u_p", system.nu)
    xi = ocp.parameter("xi", sets.X_E.n_rows, N)
    xi_N = ocp.parameter("xi_N", 1)
    ocp.state_constraint(sets.X_E, tightening=deltas, slack=xi + eps)   # (5.16e)
    ocp.terminal_cbf(h_f, slack=xi_N + eps)                             # (5.16f)
    syms = _syms(ocp, x0, u_p, error)
    ocp.minimize(objective(ocp, syms) if objective is not None
                 else squared_norm(syms["u0"] - u_p, label="filter"))
    return ocp


def _syms(ocp: OCP, x0: ca.SX, u_p: ca.SX | None, error: ErrorSet) -> dict:
    u0 = ocp.u[:, 0]
    if error.K is not None:
        u0 = u0 + ca.mtimes(ca.DM(error.K), x0 - ocp.x[:, 0])
    return {"x0": x0, "u_p": u_p, "z": ocp.x, "v": ocp.u, "u0": u0}


def fuel_objective(ocp: OCP, syms: dict) -> Cost:
    """``J = Σ_i ‖v_i‖₁`` (rendezvous, SPEC §3.4)."""
    return sum_norms(syms["v"], 1, label="fuel")


# -- value functions and candidates ---------------------------------------------------------------
def slack_cost(xi: np.ndarray, xi_N: float, alpha_f: float, slack_norm: int | float = 1
               ) -> float:
    """``h̃(ξ) = α_f ξ_N + Σ_i ‖ξ_i‖`` (SPEC §1.12); ``xi`` has one column per step."""
    xi = as_matrix(xi, "slack_cost: xi")
    xi_N = as_scalar(xi_N, "slack_cost: xi_N")
    alpha_f = positive(alpha_f, "slack_cost: alpha_f")
    check_norm_order(slack_norm, "slack_cost: slack_norm")
    return float(alpha_f * xi_N
                 + sum(np.linalg.norm(xi[:, i], slack_norm) for i in range(xi.shape[1])))


@dataclass
class Candidate:
    """A candidate (warm start) ``(z̃, ṽ, ξ̃, ξ̃_N)`` for the next step ((5.17), (6.14))."""

    z: np.ndarray
    v: np.ndarray
    xi: np.ndarray
    xi_N: float

    def as_dict(self) -> dict[str, np.ndarray]:
        return {"z": self.z, "v": self.v, "xi": self.xi, "xi_N": np.array([[self.xi_N]])}


def robust_candidate(system: System, X_E: Polytope, h_f: Callable, pi_f: Callable,
                     deltas: np.ndarray, z: np.ndarray, v: np.ndarray, xi: np.ndarray,
                     U_E: Polytope | None = None) -> Candidate:
    """(5.17) / (6.14a–c) from a feasible ``(z, v, ξ)`` at time ``k``:

    * ``ṽ = (v_1, …, v_{N−1}, v_f)``, ``z̃ = (z_1, …, z_N, f(z_N, v_f, 0))`` with
      ``v_f = π_f(z_N)`` (6.14a), or, when ``U_E`` is given and ``π_f(z_N) ∉ U ⊖ κ(E)``
      (``z_N`` outside ``D_f``), the input of :func:`terminal_input` ("any input satisfying the
      ``h_f`` decrease within ``U ⊖ κ(E)``", (5.17));
    * ``ξ̃_i = max(0, ξ_{i+1} + (Δ_i − Δ_{i+1}) 1)`` for ``i ∈ I[0, N−2]`` (SPEC [Typo?]:
      ``ξ_{i+1|k}``), ``ξ̃_{N−1} = max(0, c_x^E(z_N) + Δ_{N−1} 1)`` (SPEC [Gap]: ``c_x^E``),
      ``ξ̃_N = max(0, h_f(z̃_N))``.
    """
    z = np.asarray(z, dtype=float)
    v = np.asarray(v, dtype=float).reshape(system.nu, -1)
    xi = np.asarray(xi, dtype=float).reshape(X_E.n_rows, -1)
    N = v.shape[1]
    deltas = np.asarray(deltas, dtype=float).reshape(-1)
    if deltas.size != N or z.shape != (system.nx, N + 1):
        raise BalustradeError(f"robust_candidate: expected z of shape {(system.nx, N + 1)} and "
                              f"{N} tightenings, got {z.shape} and {deltas.size}")
    zN = z[:, N]
    u_f = terminal_input(system, h_f, pi_f, zN, U_E)
    z_next = np.asarray(system.step(zN, u_f, np.zeros(system.nw) if system.nw else None),
                        dtype=float).reshape(-1)
    z_t = np.column_stack([z[:, 1:], z_next])
    v_t = np.column_stack([v[:, 1:], u_f]) if N > 1 else u_f.reshape(-1, 1)
    xi_t = np.zeros_like(xi)
    for i in range(N - 1):
        xi_t[:, i] = np.maximum(0.0, xi[:, i + 1] + (deltas[i] - deltas[i + 1]))
    xi_t[:, N - 1] = np.maximum(0.0, X_E.H @ zN - X_E.h + deltas[N - 1])
    xi_N = max(0.0, float(h_f(z_next)))
    return Candidate(z_t, v_t, xi_t, xi_N)


def terminal_input(system: System, h_f: Callable, pi_f: Callable, z_N: np.ndarray,
                   U_E: Polytope | None = None) -> np.ndarray:
    """``v*_k(z_N)`` of (5.17): ``π_f(z_N)`` if it lies in ``U ⊖ κ(E)`` (always on ``D_f``,
    Assumption 6.14), otherwise ``argmin_{v ∈ U ⊖ κ(E)} h_f(f(z_N, v, 0))`` — the largest
    decrease of ``h_f`` any admissible input achieves (a small SLSQP problem)."""
    u_f = np.asarray(pi_f(z_N), dtype=float).reshape(-1)
    if U_E is None or U_E.contains(u_f, tol=1e-12):
        return u_f
    import scipy.optimize

    w0 = np.zeros(system.nw) if system.nw else None

    def value(v: np.ndarray) -> float:
        return float(h_f(np.asarray(system.step(z_N, v, w0), dtype=float).reshape(-1)))

    start = _project_polytope(u_f, U_E)
    res = scipy.optimize.minimize(value, start, method="SLSQP",
                                  constraints=[{"type": "ineq",
                                                "fun": lambda v: U_E.h - U_E.H @ v,
                                                "jac": lambda v: -U_E.H}],
                                  options={"ftol": 1e-12, "maxiter": 200})
    v = np.asarray(res.x, dtype=float)
    if not U_E.contains(v, tol=1e-12):
        v = _project_polytope(v, U_E)
    return v if value(v) <= value(start) else start


def _project_polytope(u: np.ndarray, U: Polytope) -> np.ndarray:
    from balustrade.dsl.sets import Box

    if isinstance(U, Box) or (np.allclose(np.abs(U.H).sum(axis=1), 1.0)
                              and np.all(np.count_nonzero(U.H, axis=1) == 1)):
        lb, ub = U.bounding_box().lb, U.bounding_box().ub
        return np.clip(u, lb, ub)
    import cvxpy as cp

    v = cp.Variable(u.size)
    cp.Problem(cp.Minimize(cp.sum_squares(v - u)), [U.H @ v <= U.h]).solve(solver="CLARABEL")
    return np.asarray(v.value, dtype=float).reshape(-1)


def terminal_cbf_with_domain(A: np.ndarray, B: np.ndarray, X_E: Polytope, U_E: Polytope,
                             delta_N: float, level: float = 1.0,
                             decrease_factor: float = 0.99):
    """The terminal CBF SDP (6.17) with the input LMI imposed on ``U ⊖ κ(E)`` scaled by
    ``1/sqrt(1 + level)``, so that ``π_f(x) = Kx ∈ U ⊖ κ(E)`` on ``D_f = {h_f <= γ_f}`` with
    ``γ_f >= level`` (SPEC §2.27 [Gap] on ``γ_f``). The printed SDP (``level = 0``) makes the
    ellipsoid touch the input constraint, so ``γ_f ≈ 0`` and ``D_r = {h_r <= α_f γ_f}`` of
    Theorem 5.15 collapses onto ``S_r``; a positive level gives the decrease guarantee a
    region. The ellipsoid stays inside ``X ⊖ E`` and ``U ⊖ κ(E)`` as the thesis requires."""
    from balustrade.problems.terminal_cbf import synthesize_terminal_cbf

    level = nonnegative(level, "terminal_cbf_with_domain: level")
    check_instance(U_E, Polytope, "terminal_cbf_with_domain: U_E")
    return synthesize_terminal_cbf(A, B, X_E, U_E, delta_N=delta_N,
                                   decrease_factor=decrease_factor, min_level=level)


def minimal_slacks(X_E: Polytope, h_f: Callable, deltas: np.ndarray, z: np.ndarray
                   ) -> tuple[np.ndarray, float]:
    """The smallest slacks a nominal trajectory ``z`` needs in (5.15e–f):
    ``ξ_i = max(0, c_x^E(z_i) + Δ_i 1)``, ``ξ_N = max(0, h_f(z_N))`` (SPEC §1.4).

    Applied to an interior-point optimizer of (5.15)/(6.15) it removes the barrier's slack
    residue (IPOPT leaves ``α_f ξ_N ≈ 10⁻⁶…10⁻⁵`` on ``S_r``) without changing ``z``, so the
    polished ``h̃`` is an upper bound on ``h_r`` at least as tight as the solver's value."""
    z = np.asarray(z, dtype=float)
    deltas = np.asarray(deltas, dtype=float).reshape(-1)
    N = deltas.size
    xi = np.maximum(0.0, X_E.H @ z[:, :N] - X_E.h[:, None] + deltas[None, :])
    return xi, max(0.0, float(h_f(z[:, N])))


def polished_slacks(solution, X_E: Polytope, h_f: Callable, deltas: np.ndarray
                    ) -> tuple[np.ndarray, float]:
    """Elementwise minimum of a solution's slacks and :func:`minimal_slacks` of its ``z``."""
    xi = np.maximum(np.asarray(solution["xi"], dtype=float).reshape(X_E.n_rows, -1), 0.0)
    xi_N = max(float(np.asarray(solution["xi_N"]).reshape(-1)[0]), 0.0)
    xi_min, xi_N_min = minimal_slacks(X_E, h_f, deltas, solution["z"])
    return np.minimum(xi, xi_min), min(xi_N, xi_N_min)
