"""The numbers Algorithms 5.2 and 6.4 compute between their solves, as CasADi functions:
the one definition that the Python controllers evaluate and the C emitters generate code
from (:mod:`balustrade.codegen.emit_robust`), so that C and Python round alike (issue #14,
"C = Python along closed loops"; docs/vehicles.md, "session 13").

* :func:`slack_cost_expr` — ``h̃(ξ) = α_f ξ_N + Σ_i ‖ξ_i‖`` (SPEC §1.12), summed left to
  right from ``α_f ξ_N``;
* :func:`polish_expr` — the polished slacks of :func:`~balustrade.control.robust_steps.
  polished_slacks` (elementwise minimum of the solver's slacks, clipped at 0, and the
  slacks its ``z`` needs) and their ``h̃``;
* :func:`candidate_function` — the shifted candidate (5.17)/(6.14) of
  :func:`~balustrade.control.robust_steps.robust_candidate` with its ``h̃`` and whether its
  terminal input is exact (:func:`terminal_input_expr`).

:class:`TubeFunctions` holds them for one controller; :meth:`TubeFunctions.build` returns
``None`` when ``h_f`` or ``π_f`` have no CasADi form (then the controllers use the numpy
functions of :mod:`~balustrade.control.robust_steps`, whose sums and products BLAS may order
differently — such a controller cannot be emitted anyway).

``π_f``: give it as an expression (:class:`~balustrade.dsl.policies.AffinePolicy`, a
``casadi.Function``). A numpy-only ``π_f`` is replaced in Python by the affine map probed
from calls of it, checked against ``π_f(z_N)`` at every candidate (:func:`policy_expr`,
:data:`POLICY_TOL`); the C emitters refuse it (``fit_policy=False``), since the C has no such
check (session 13, docs/vehicles.md "Session 13: π_f in C").

Why: session 13 traced the first bit that differed between Python and C along the lane
change: every solve (SQP, its QP, the interior-point retry) returned bitwise the same point
from the same data, but ``h_r``, ``h̃``, ``h_cand`` and the input differed by one rounding
(2.2e-16) because numpy summed ``h̃`` pairwise and computed ``d·P·d`` and ``K e`` with
BLAS, while the C summed left to right. Those 1e-16 grew to 1e-8 in later solves and, where
attempts of the retry chain answer at nearby states, to 1e-3.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import casadi as ca
import numpy as np

from balustrade.control.robust_steps import (
    CONTAINS_TOL,
    Candidate,
    polished_slacks,
    robust_candidate,
    slack_cost,
)
from balustrade.dsl.sets import Polytope
from balustrade.dsl.system import System
from balustrade.errors import BalustradeError

#: how far the affine map identified for a numpy-only ``π_f`` (:func:`policy_expr`) may be
#: from ``π_f(z_N)`` for the CasADi candidate to be used (the tolerance of the
#: identification; on the lane change the two differ by rounding only)
POLICY_TOL = 1e-9


def norm_expr(col: ca.SX, order: float) -> ca.SX:
    """``‖col‖`` for the slack norms 1, 2 and ∞ (CasADi sums left to right)."""
    if order == 1:
        return ca.norm_1(col)
    if order == 2:
        return ca.norm_2(col)
    if np.isinf(order):
        return ca.norm_inf(col)
    raise BalustradeError(f"slack norm {order!r}: the tube functions support 1, 2 and inf")


def slack_cost_expr(xi: ca.SX, xi_N: ca.SX, alpha_f: float, slack_norm: float) -> ca.SX:
    """``h̃(ξ) = α_f ξ_N + Σ_i ‖ξ_i‖`` (SPEC §1.12), one column of ``xi`` per step."""
    total = alpha_f * xi_N
    for i in range(xi.shape[1]):
        total += norm_expr(xi[:, i], slack_norm)
    return total


def symbolic_policy(nu: int, pi_f: Callable, z: ca.SX) -> ca.SX | None:
    """``π_f(z)`` when ``π_f`` accepts CasADi symbols (``nu`` entries), else ``None``."""
    try:
        out = pi_f(z)
        if isinstance(out, (ca.SX, ca.MX, ca.DM)) and out.numel() == nu:
            return ca.reshape(ca.SX(out) if isinstance(out, ca.DM) else out, nu, 1)
    except Exception:  # noqa: BLE001 - a numpy-only policy
        pass
    return None


def policy_expr(nx: int, nu: int, pi_f: Callable, z: ca.SX, fit: bool = True) -> ca.SX:
    """``π_f(z)`` on CasADi symbols: ``π_f`` itself if it accepts them (e.g. a
    :class:`~balustrade.dsl.policies.AffinePolicy` or a ``casadi.Function``); else, with
    ``fit``, the linear map it is checked to be (``π_f(x) = K_f x + c`` at random points),
    else a BalustradeError naming ``pi_f``. The check cannot see a numpy-only ``π_f`` that is
    affine only where it was probed (e.g. saturating at large ``|Kx|``):
    :meth:`TubeFunctions.candidate` compares the map with ``π_f`` at every ``z_N`` it is used
    at; the C emitters pass ``fit=False`` (no such check runs in C,
    :func:`~balustrade.codegen.emit_robust.emit_robust`)."""
    out = symbolic_policy(nu, pi_f, z)
    if out is not None:
        return out
    if not fit:
        raise BalustradeError(f"the terminal policy pi_f ({_describe(pi_f)}) does not accept "
                              f"CasADi symbols (or gives no {nu} entries on a state of {nx}): "
                              f"{PI_F_HINT.format(nx=nx, nu=nu)}")
    try:
        c = np.asarray(pi_f(np.zeros(nx)), dtype=float).reshape(nu)
        K = np.column_stack([np.asarray(pi_f(e), dtype=float).reshape(nu) - c
                             for e in np.eye(nx)])
        rng = np.random.default_rng(0)
        for x in rng.standard_normal((3, nx)) * 3:
            y = np.asarray(pi_f(x), dtype=float).reshape(nu)
            if not np.allclose(y, K @ x + c, rtol=1e-9, atol=1e-9):
                raise ValueError("not linear")
    except Exception as exc:  # noqa: BLE001
        raise BalustradeError("the terminal policy pi_f must accept CasADi symbols or be "
                              "affine (checked at random points)") from exc
    return ca.mtimes(ca.DM(K), z) + ca.DM(c)


def _describe(pi_f: Callable) -> str:
    """``pi_f``'s name for an error message (``TerminalCBF.policy``, ``<lambda>``, …)."""
    return getattr(pi_f, "__qualname__", None) or type(pi_f).__name__


#: how to pass a ``π_f`` whose C computes what Python computes (:func:`policy_expr`)
PI_F_HINT = ("pass it as an explicit law, balustrade.dsl.AffinePolicy(K, k, x_s) for "
             "pi_f(x) = K (x - x_s) + k (e.g. AffinePolicy(cbf.K) for a terminal CBF's "
             "policy K x), or a casadi.Function of x ({nx} entries) with {nu} outputs")


def terminal_input_expr(system: System, h_f: Callable, pi_f: Callable, U_E: Polytope,
                        zN: ca.SX, fit: bool = True) -> tuple[ca.SX, ca.SX]:
    """``(v_f, exact)``: the terminal input of (5.17)
    (:func:`~balustrade.control.robust_steps.terminal_input`) — ``π_f(z_N)`` when it lies in
    ``U ⊖ κ(E)``; otherwise, for one input with ``h_f(f(z_N, v, 0))`` quadratic in ``v``, its
    minimizer over the interval ``U ⊖ κ(E)`` in closed form — and whether it is exact
    (``exact = 0``: outside, and no closed form). ``fit``: as in :func:`policy_expr`."""
    H, h = np.asarray(U_E.H, dtype=float), np.asarray(U_E.h, dtype=float)
    u_f = policy_expr(system.nx, system.nu, pi_f, zN, fit)
    inside = ca.mmin(ca.DM(h) + CONTAINS_TOL - ca.mtimes(ca.DM(H), u_f)) >= 0
    if system.nu != 1:
        return u_f, inside
    v = ca.SX.sym("v_f", 1)
    w0 = ca.DM.zeros(system.nw) if system.nw else None
    q = h_f(system(zN, v, w0) if w0 is not None else system(zN, v))
    hess = ca.hessian(q, v)[0]
    if ca.depends_on(hess, ca.vertcat(zN, v)) or float(ca.DM(hess)) <= 0:
        return u_f, inside
    a = float(ca.DM(hess))
    b = ca.substitute(ca.jacobian(q, v), v, 0)
    col = H[:, 0]
    lo = max((h[i] / col[i] for i in range(len(h)) if col[i] < 0), default=-np.inf)
    hi = min((h[i] / col[i] for i in range(len(h)) if col[i] > 0), default=np.inf)
    v_min = ca.fmin(ca.fmax(-b / a, lo), hi)
    return ca.if_else(inside, u_f, v_min), ca.SX(1)


def polish_expr(X_E: Polytope, h_f: Callable, deltas: np.ndarray, alpha_f: float,
                slack_norm: float, z: ca.SX, xi: ca.SX, xi_N: ca.SX
                ) -> tuple[ca.SX, ca.SX, ca.SX]:
    """``(ξ, ξ_N, h̃)`` polished (:func:`~balustrade.control.robust_steps.polished_slacks`):
    ``min(max(ξ, 0), max(0, c_x^E(z_i) + Δ_i))``, ``min(max(ξ_N, 0), max(h_f(z_N), 0))``
    and ``h̃`` of them."""
    deltas = np.asarray(deltas, dtype=float).reshape(-1)
    N, nr = deltas.size, X_E.H.shape[0]
    Hx, hx = ca.DM(np.asarray(X_E.H, dtype=float)), ca.DM(np.asarray(X_E.h, dtype=float))
    xi = ca.fmax(xi, 0)
    xi_N = ca.fmax(xi_N, 0)
    need = ca.fmax(ca.mtimes(Hx, z[:, :N]) - ca.repmat(hx, 1, N)
                   + ca.repmat(ca.DM(deltas).T, nr, 1), 0)
    xi_p = ca.fmin(xi, need)
    xi_N_p = ca.fmin(xi_N, ca.fmax(h_f(z[:, N]), 0))
    return xi_p, xi_N_p, slack_cost_expr(xi_p, xi_N_p, alpha_f, slack_norm)


def candidate_function(sym: str, system: System, X_E: Polytope, U_E: Polytope,
                       h_f: Callable, pi_f: Callable, deltas: np.ndarray, alpha_f: float,
                       slack_norm: float, fit_policy: bool = True) -> ca.Function:
    """``sym(z, v, ξ) -> (z̃, ṽ, vec ξ̃, ξ̃_N, h̃(ξ̃), exact)``: the candidate (5.17)/(6.14)
    (:func:`~balustrade.control.robust_steps.robust_candidate`; ``exact``: its terminal input
    is the one Python's numpy path computes, :func:`terminal_input_expr`). ``fit_policy=False``
    (the C emitters): a numpy-only ``π_f`` is a BalustradeError naming ``pi_f``, not an
    affine map identified from calls (:func:`policy_expr`)."""
    nx, nu = system.nx, system.nu
    deltas = np.asarray(deltas, dtype=float).reshape(-1)
    N, nr = deltas.size, X_E.H.shape[0]
    Hx, hx = ca.DM(np.asarray(X_E.H, dtype=float)), ca.DM(np.asarray(X_E.h, dtype=float))
    zc, vc, xic = ca.SX.sym("z", nx, N + 1), ca.SX.sym("v", nu, N), ca.SX.sym("xi", nr, N)
    zN = zc[:, N]
    u_f, exact = terminal_input_expr(system, h_f, pi_f, U_E, zN, fit_policy)
    w0 = ca.DM.zeros(system.nw) if system.nw else None
    z_next = system(zN, u_f, w0) if w0 is not None else system(zN, u_f)
    z_t = ca.horzcat(zc[:, 1:], z_next)
    v_t = ca.horzcat(vc[:, 1:], u_f) if N > 1 else u_f
    cols = [ca.fmax(xic[:, i + 1] + (deltas[i] - deltas[i + 1]), 0) for i in range(N - 1)]
    cols.append(ca.fmax(ca.mtimes(Hx, zN) - hx + deltas[N - 1], 0))
    xi_t = ca.horzcat(*cols)
    xi_N_t = ca.fmax(h_f(z_next), 0)
    return ca.Function(sym, [zc, vc, xic],
                       [z_t, v_t, ca.vec(xi_t), xi_N_t,
                        slack_cost_expr(xi_t, xi_N_t, alpha_f, slack_norm), exact],
                       ["z", "v", "xi"], ["z_next", "v_next", "xi_next", "xi_N_next",
                                          "h_cand", "exact"])


@dataclass
class TubeFunctions:
    """The CasADi functions of one tube controller (module docstring), evaluated in Python:
    ``cost(ξ, ξ_N)``, ``polish(z, ξ, ξ_N)`` and ``candidate(z, v, ξ)``."""

    nx: int
    nu: int
    nr: int
    N: int
    cost_fn: ca.Function
    polish_fn: ca.Function
    cand_fn: ca.Function
    #: for a numpy-only ``π_f``: ``(π_f, the affine map policy_expr identified)``, checked
    #: against each other at every candidate's ``z_N`` (``None``: ``π_f`` is symbolic)
    policy_check: tuple[Callable, ca.Function] | None = None

    @classmethod
    def build(cls, system: System, X_E: Polytope, U_E: Polytope, h_f: Callable,
              pi_f: Callable, deltas: np.ndarray, alpha_f: float, slack_norm: float
              ) -> TubeFunctions | None:
        """The functions of a controller, or ``None`` when ``h_f`` or ``π_f`` have no
        CasADi form, ``h_f`` is not scalar or the system takes parameters θ (the numpy path
        of :mod:`~balustrade.control.robust_steps` is used then)."""
        deltas = np.asarray(deltas, dtype=float).reshape(-1)
        N, nr, nx, nu = deltas.size, X_E.H.shape[0], system.nx, system.nu
        try:
            if getattr(system, "ntheta", 0):
                return None
            z, xi, xi_N = ca.SX.sym("z", nx, N + 1), ca.SX.sym("xi", nr, N), ca.SX.sym("xN")
            hz = h_f(z[:, N])
            if not isinstance(hz, (ca.SX, ca.MX, ca.DM)) or hz.numel() != 1:
                return None
            xi_p, xi_N_p, h = polish_expr(X_E, h_f, deltas, alpha_f, slack_norm, z, xi, xi_N)
            polish = ca.Function("tube_polish", [z, xi, xi_N], [xi_p, xi_N_p, h])
            cost = ca.Function("tube_cost", [xi, xi_N],
                               [slack_cost_expr(xi, xi_N, alpha_f, slack_norm)])
            cand = candidate_function("tube_cand", system, X_E, U_E, h_f, pi_f, deltas,
                                      alpha_f, slack_norm)
            zN = ca.SX.sym("zN", nx)
            check = None if symbolic_policy(nu, pi_f, zN) is not None else (
                pi_f, ca.Function("tube_policy", [zN], [policy_expr(nx, nu, pi_f, zN)]))
        except Exception:  # noqa: BLE001 - no CasADi form: the numpy path is used
            return None
        return cls(nx, nu, nr, N, cost, polish, cand, check)

    def cost(self, xi: np.ndarray, xi_N: float) -> float:
        """``h̃(ξ)`` (the C's sum order)."""
        xi = np.asarray(xi, dtype=float).reshape(self.nr, self.N)
        return float(self.cost_fn(xi, float(xi_N)))

    def polish(self, solution: object) -> tuple[np.ndarray, float]:
        """The polished slacks ``(ξ, ξ_N)`` of a solution with ``z``, ``xi``, ``xi_N``."""
        xi_N = float(np.asarray(solution["xi_N"], dtype=float).reshape(-1)[0])
        xi, xN, _ = self.polish_fn(np.asarray(solution["z"], dtype=float),
                                   np.asarray(solution["xi"], dtype=float)
                                   .reshape(self.nr, self.N), xi_N)
        return np.asarray(xi), float(xN)

    def candidate(self, z: np.ndarray, v: np.ndarray, xi: np.ndarray) -> Candidate | None:
        """The candidate (5.17)/(6.14); ``None`` where its terminal input has no closed form
        or, for a numpy-only ``π_f``, where the affine map identified for it differs from
        ``π_f(z_N)`` (beyond :data:`POLICY_TOL`) (the caller computes it as
        :func:`~balustrade.control.robust_steps.robust_candidate` does)."""
        if self.policy_check is not None:
            pi_f, affine = self.policy_check
            zN = np.asarray(z, dtype=float).reshape(self.nx, self.N + 1)[:, self.N]
            want = np.asarray(pi_f(zN), dtype=float).reshape(-1)
            got = np.asarray(affine(zN), dtype=float).reshape(-1)
            if not np.allclose(got, want, rtol=POLICY_TOL, atol=POLICY_TOL):
                return None
        out = self.cand_fn(np.asarray(z, dtype=float),
                           np.asarray(v, dtype=float).reshape(self.nu, self.N),
                           np.asarray(xi, dtype=float).reshape(self.nr, self.N))
        if not float(out[5]) > 0.5:
            return None
        return Candidate(np.asarray(out[0]), np.asarray(out[1]).reshape(self.nu, self.N),
                         np.asarray(out[2]).reshape(self.nr, self.N, order="F"),
                         float(out[3]))




def tube_cost(tube: TubeFunctions | None, xi: np.ndarray, xi_N: float, alpha_f: float,
              slack_norm: float = 1) -> float:
    """``h̃(ξ)``: :meth:`TubeFunctions.cost`, else :func:`~balustrade.control.robust_steps.
    slack_cost` (numpy)."""
    if tube is None:
        return slack_cost(xi, xi_N, alpha_f, slack_norm)
    return tube.cost(xi, xi_N)


def tube_polished(tube: TubeFunctions | None, solution: object, X_E: Polytope,
                  h_f: Callable, deltas: np.ndarray) -> tuple[np.ndarray, float]:
    """The polished slacks: :meth:`TubeFunctions.polish`, else
    :func:`~balustrade.control.robust_steps.polished_slacks` (numpy)."""
    if tube is None:
        return polished_slacks(solution, X_E, h_f, deltas)
    return tube.polish(solution)


def tube_candidate(tube: TubeFunctions | None, system: System, X_E: Polytope, h_f: Callable,
                   pi_f: Callable, deltas: np.ndarray, z: np.ndarray, v: np.ndarray,
                   xi: np.ndarray, U_E: Polytope | None = None) -> Candidate:
    """The candidate (5.17)/(6.14): :meth:`TubeFunctions.candidate` where it is exact, else
    :func:`~balustrade.control.robust_steps.robust_candidate` (numpy; its terminal input by
    SLSQP where π_f leaves ``U ⊖ κ(E)`` and no closed form exists)."""
    cand = None if tube is None else tube.candidate(z, v, xi)
    if cand is None:
        cand = robust_candidate(system, X_E, h_f, pi_f, deltas, z, v, xi, U_E)
    return cand


__all__ = ["CONTAINS_TOL", "PI_F_HINT", "POLICY_TOL", "TubeFunctions", "candidate_function",
           "norm_expr", "policy_expr", "polish_expr", "slack_cost_expr", "symbolic_policy",
           "terminal_input_expr", "tube_candidate", "tube_cost", "tube_polished"]
