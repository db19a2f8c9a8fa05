"""The horizon-free approximate PCBF problems (thesis Section 7.2, SPEC §2.28).

Given an explicit approximation ``ĥ`` of the PCBF ``h_PB`` (2.24) or of the extended
``h`` (7.7) — a trained network exported to CasADi, or any hand-written function:

* :func:`max_decrease_problem` — (7.6): ``Δĥ(x) = ĥ(x) − min_{u ∈ U} ĥ(f(x, u))``; the OCP
  minimizes ``ĥ(f(x, u))`` over ``u ∈ U`` (a nonconvex NLP in ``u`` only);
* :func:`approximate_filter_problem` — (7.5): ``min ‖u − u_p‖²`` s.t.
  ``ĥ(f(x, u)) − ĥ(x) <= −ρ Δĥ(x)`` and ``u ∈ U``, ``ρ ∈ (0, 1]``;
* :class:`MaximalDecrease` — (7.6) solved by multi-start (SPEC §2.28 default: starts at
  ``u = 0``, ``u_p`` and a coarse grid over ``U``): all candidates are screened by one
  batched evaluation of ``ĥ(f(x, ·))`` and the local solver is run from the best ones.

Neither problem depends on the prediction horizon ``N`` of (2.24): ``ĥ`` carries it.
By Proposition 7.3 the minimizer of (7.6) is feasible in (7.5) for every ``x`` and every
``ρ ∈ (0, 1]``; the filter is warm-started with it.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable
from dataclasses import dataclass

import casadi as ca
import numpy as np

from balustrade._checks import as_count, check_name, check_symbolic
from balustrade.backends import Compiled, Solution, compile
from balustrade.backends.casadi_fast import Buffered, FastNLP
from balustrade.dsl import OCP, Set, System, squared_norm
from balustrade.dsl.sets import Box
from balustrade.errors import BalustradeError, ShapeError
from balustrade.problems._args import check_system_sets, nonnegative

HHat = ca.Function | Callable[[ca.SX], object]


def as_h_function(h_hat: HHat, nx: int, name: str = "h_hat") -> ca.Function:
    """Normalize ``ĥ`` (a CasADi Function ``x ↦ ĥ(x)`` or a callable on an ``(nx, 1)`` SX
    symbol) to a CasADi Function with one input of shape ``(nx, 1)`` and a scalar output."""
    check_name(name, "as_h_function: name")
    nx = as_count(nx, f"{name}: nx", low=1)
    if isinstance(h_hat, ca.Function):
        if h_hat.n_in() != 1 or h_hat.size1_in(0) * h_hat.size2_in(0) != nx:
            raise ShapeError(f"{name}: input of the CasADi Function", (nx, 1),
                             (h_hat.size1_in(0), h_hat.size2_in(0)))
        if h_hat.numel_out(0) != 1:
            raise ShapeError(f"{name}: output of the CasADi Function", "a scalar",
                             (h_hat.size1_out(0), h_hat.size2_out(0)))
        return h_hat
    if not callable(h_hat):
        raise BalustradeError(f"{name}: ĥ must be a CasADi Function or a callable on an "
                              f"({nx}, 1) symbol, got {type(h_hat).__name__}")
    x = ca.SX.sym("x", nx)
    try:
        value = ca.SX(h_hat(x))
    except Exception as exc:  # the user's function failed on a symbol
        raise BalustradeError(f"{name}: ĥ(x) failed on a symbol of shape ({nx}, 1): {exc}"
                              ) from exc
    if value.numel() != 1:
        raise ShapeError(f"{name}: ĥ(x)", "a scalar", value.shape)
    check_symbolic(value, f"{name}: ĥ(x)")
    return ca.Function(name, [x], [value], ["x"], ["h"])


def _input_variable(ocp: OCP, U: Set, nu: int) -> ca.SX:
    """``u ∈ U``: simple bounds for a box (cheapest for IPOPT), rows ``c_U(u) <= 0`` else."""
    if U.dim != nu:
        raise ShapeError(f"{ocp.name}: input set {U.name}", f"dimension {nu}",
                         f"dimension {U.dim}")
    if isinstance(U, Box):
        return ocp.variable("u", nu, lb=U.lb, ub=U.ub, role="input")
    u = ocp.variable("u", nu, role="input")
    ocp.le(U.c(u), 0, name="input", tag="input")
    return u


def max_decrease_problem(system: System, U: Set, h_hat: HHat,
                         name: str = "approx_max_decrease") -> OCP:
    """(7.6) as ``min_{u ∈ U} ĥ(f(x0, u))``; ``Δĥ(x0) = ĥ(x0) − optimum``.

    Parameters: ``x0``. Variable: ``u``.
    """
    check_system_sets(name, system, U=U)
    h = as_h_function(h_hat, system.nx)
    ocp = OCP(None, name=name)
    u = _input_variable(ocp, U, system.nu)
    x0 = ocp.parameter("x0", system.nx)
    ocp.minimize(h(system(x0, u)))
    return ocp


def approximate_filter_problem(system: System, U: Set, h_hat: HHat, eps: float = 1e-6,
                               name: str = "approx_filter") -> OCP:
    """(7.5): ``min ‖u − u_p‖²`` s.t. ``ĥ(f(x0, u)) − ĥ(x0) <= −ρ Δĥ + eps`` and ``u ∈ U``
    (for ``Δĥ < 0`` the bound is extended as in :func:`decrease_bound`).

    Parameters: ``x0``, ``u_p``, ``dh`` (``Δĥ(x0)`` from (7.6)) and ``rho`` (``ρ ∈ (0, 1]``,
    default 1), so one compiled problem serves every ``ρ``. ``eps`` is the numerical margin
    that keeps the (7.6) minimizer strictly feasible at ``ρ = 1`` (Proposition 7.3).
    """
    check_system_sets(name, system, U=U)
    eps = nonnegative(eps, f"{name}: eps")
    h = as_h_function(h_hat, system.nx)
    ocp = OCP(None, name=name)
    u = _input_variable(ocp, U, system.nu)
    x0 = ocp.parameter("x0", system.nx)
    u_p = ocp.parameter("u_p", system.nu)
    dh = ocp.parameter("dh", 1)
    rho = ocp.parameter("rho", 1, value=1.0)
    ocp.decrease(h(system(x0, u)) - h(x0), decrease_bound(dh, rho) + eps,
                 name="approx_decrease")
    ocp.minimize(squared_norm(u - u_p, label="filter"))
    return ocp


def solver_options(solver: str, options: dict | None = None) -> dict | None:
    """Options for the small (7.5)/(7.6) NLPs: with ``sqpmethod``, Hessian convexification
    by eigenvalue clipping (CasADi 3.8's ``regularize`` corrupts the heap on these
    one-input problems when started at a bound of ``U``)."""
    if solver == "sqpmethod":
        return {"convexify_strategy": "eigen-clip", **(options or {})}
    return options


def decrease_bound(dh: object, rho: object) -> object:
    """Right side of (7.5): ``max(−ρ Δĥ, −Δĥ)``, i.e. ``−ρ Δĥ`` when ``Δĥ >= 0`` (the
    thesis' bound) and ``−Δĥ`` when ``Δĥ < 0`` (works on numbers and CasADi symbols).

    [Gap] Proposition 7.3 uses ``−Δĥ <= −ρ Δĥ``, true only for ``Δĥ >= 0`` (a CBF outside
    ``S_PB``). A learned ``ĥ``, or the extended ``h`` inside ``S_PB``, can have ``Δĥ < 0``
    (no input decreases it); then ``−ρ Δĥ < −Δĥ`` and (7.5) would be infeasible for
    ``ρ < 1``. With the bound above the (7.6) minimizer is feasible for every ``x`` and
    ``ρ ∈ (0, 1]``, the bound is continuous in ``Δĥ``, and where ``ĥ`` cannot decrease the
    filter asks for the least increase (``ĥ(f(x, u)) <= min_v ĥ(f(x, v))``), which keeps
    the next state in ``{ĥ <= 0}`` whenever some input can.
    """
    fmax = ca.fmax if isinstance(dh, (ca.SX, ca.MX, ca.DM)) else np.maximum
    return fmax(-rho * dh, -dh)


def coarse_grid(U: Set, points_per_dim: int = 5, max_points: int = 125) -> np.ndarray:
    """A coarse grid over the bounding box of ``U`` (rows are inputs), kept to points of
    ``U``; with too many dimensions, the box vertices and centre instead."""
    points_per_dim = as_count(points_per_dim, "coarse_grid: points_per_dim", low=1)
    max_points = as_count(max_points, "coarse_grid: max_points", low=1)
    box = U if isinstance(U, Box) else U.bounding_box()
    lb, ub = np.asarray(box.lb, float), np.asarray(box.ub, float)
    if not (np.all(np.isfinite(lb)) and np.all(np.isfinite(ub))):
        return np.zeros((1, U.dim))
    if points_per_dim ** U.dim <= max_points:
        axes = [np.linspace(lo, hi, points_per_dim) for lo, hi in zip(lb, ub)]
        grid = np.array(list(itertools.product(*axes)), dtype=float)
    else:
        corners = np.array(list(itertools.product(*zip(lb, ub))), dtype=float)[:max_points - 1]
        grid = np.vstack([corners, 0.5 * (lb + ub)])
    return grid[U.contains_many(grid)] if not isinstance(U, Box) else grid


@dataclass
class DecreaseResult:
    """Result of (7.6) at one state: the minimizer ``u``, ``ĥ(x)``, ``min ĥ(f(x, u))``,
    ``Δĥ(x)``, the local solutions tried (:class:`Solution` objects of the compiled
    problem; empty when every local solve took the fast path), the projected proposal
    ``u_proposal = clip_U(u_p)`` (a screening candidate) with ``h_proposal =
    ĥ(f(x, u_proposal))``, and the wall time of the whole (7.6) evaluation."""

    u: np.ndarray
    h_x: float
    h_next: float
    dh: float
    solutions: list[Solution]
    success: bool
    u_proposal: np.ndarray | None = None
    h_proposal: float = float("nan")
    solve_time: float = 0.0
    n_local_solves: int = 0
    n_kkt_starts: int = 0


class MaximalDecrease:
    """(7.6) by multi-start: screen ``{0, u_p} ∪ grid`` with one batched evaluation of
    ``ĥ(f(x, ·))``, run the compiled local solver from the ``n_local`` best candidates,
    keep the best local optimum (never worse than the best screened candidate).

    ``fast=True`` (default) evaluates the same algorithm with less overhead:

    * one :class:`Buffered` call returns ``ĥ(f(x, c))`` for all candidates ``c`` (the
      static ones — ``clip_U(0)`` and the grid, exact duplicates removed — as constants)
      and ``ĥ(x)``;
    * a start that is already a first-order KKT point of (7.6) on a box ``U`` — a vertex
      of ``U`` where ``∇_u ĥ(f(x, u))`` points out of ``U`` in every component — is
      returned without calling the solver: from there ``sqpmethod``'s QP step is zero and
      it stops at the start (IPOPT stops there to its tolerance); tested against the
      solver;
    * otherwise a :class:`FastNLP` solve, and the compiled problem's ``solve`` (with its
      retries) only when that fails.
    """

    def __init__(self, system: System, U: Set, h_hat: HHat, solver: str = "ipopt",
                 options: dict | None = None, grid_points: int = 5, n_local: int = 1,
                 fast: bool = True):
        check_system_sets("MaximalDecrease", system, U=U)
        self.system, self.U = system, U
        self.h = as_h_function(h_hat, system.nx)
        self.ocp = max_decrease_problem(system, U, self.h)
        self.compiled: Compiled = compile(self.ocp, "casadi", solver,
                                          solver_options(solver, options))
        self.grid = coarse_grid(U, grid_points)
        self.n_local = as_count(n_local, "MaximalDecrease: n_local")
        self.fast = bool(fast)
        nx, nu = system.nx, system.nu
        x, u = ca.SX.sym("x", nx), ca.SX.sym("u", nu)
        h_next = self.h(system(x, u))
        self._h_next = ca.Function("h_next", [x, u], [h_next])
        self._n_cand = len(self.grid) + 2
        self._h_next_many = self._h_next.map(self._n_cand)
        box = U if isinstance(U, Box) else U.bounding_box()
        self._lb, self._ub = np.asarray(box.lb, float), np.asarray(box.ub, float)
        self._u_zero = _project_box(np.zeros(nu), U)
        # fast path: static candidates (clip(0), then the grid without exact duplicates),
        # the dynamic one (clip(u_p)) is an input; the full candidate list of solve() is
        # [clip(0), clip(u_p), grid...] and self._index maps it into the values vector
        static: list[np.ndarray] = []
        index = []
        for c in [self._u_zero, *self.grid]:
            hit = next((k for k, s in enumerate(static) if np.array_equal(s, c)), None)
            if hit is None:
                static.append(np.asarray(c, float))
                hit = len(static) - 1
            index.append(hit + 1)  # value 0 is clip(u_p)
        self._index = np.array([index[0], 0, *index[1:]], dtype=int)
        self._cand_static = np.vstack([self._u_zero.reshape(1, nu), self.grid])
        c1 = ca.SX.sym("c1", nu)
        values = [self._h_next(x, c1)] + [self._h_next(x, ca.DM(c)) for c in static]
        self._screen = Buffered(ca.Function("screen", [x, c1],
                                            [ca.vertcat(*values), self.h(x)]))
        self._h_next_buf = Buffered(self._h_next)
        self._h_buf = Buffered(ca.Function("h", [x], [self.h(x)]))
        self._grad = Buffered(ca.Function("h_next_grad", [x, u], [ca.gradient(h_next, u)]))
        self._box = isinstance(U, Box)
        self._fast_nlp = FastNLP(self.compiled) if self.fast else None

    def h_value(self, x: np.ndarray) -> float:
        return float(self._h_buf(x)[0][0])

    def h_next(self, x: np.ndarray, u: np.ndarray) -> float:
        """``ĥ(f(x, u))`` (one evaluation: the certification test of Algorithm 7.5)."""
        return float(self._h_next_buf(x, u)[0][0])

    def solve(self, x: np.ndarray, u_p: np.ndarray | None = None) -> DecreaseResult:
        if self.fast:
            return self._solve_fast(np.asarray(x, float).reshape(-1), u_p)
        nu = self.system.nu
        u_p = np.zeros(nu) if u_p is None else np.asarray(u_p, float).reshape(nu)
        u_p_in = _project_box(u_p, self.U)
        cand = np.vstack([np.zeros((1, nu)), u_p_in.reshape(1, nu), self.grid])
        cand[0] = _project_box(cand[0], self.U)
        start = time.perf_counter()
        values = np.asarray(self._h_next_many(np.tile(np.reshape(x, (-1, 1)), self._n_cand),
                                              cand.T)).reshape(-1)
        h_proposal = float(values[1])
        values = np.where(np.isfinite(values), values, np.inf)
        order = np.argsort(values, kind="stable")
        best_u, best_v = cand[order[0]].copy(), float(values[order[0]])
        sols, success, tried = [], False, []
        for idx in order:
            if len(tried) >= self.n_local:
                break
            if any(np.allclose(cand[idx], t) for t in tried):
                continue
            tried.append(cand[idx])
            sol = self.compiled.solve({"x0": x}, warm_start={"u": cand[idx]})
            sols.append(sol)
            if sol.usable:  # a feasible point is in U: a valid (7.6) candidate
                u_loc = np.asarray(sol["u"], float).reshape(nu)
                if np.all(np.isfinite(u_loc)) and in_set(u_loc, self.U, 1e-7):
                    v = self.h_next(x, u_loc)
                    success = success or sol.success
                    if v < best_v:
                        best_u, best_v = u_loc, v
        h_x = self.h_value(x)
        return DecreaseResult(best_u, h_x, best_v, h_x - best_v, sols,
                              success or np.isfinite(best_v), u_p_in, h_proposal,
                              time.perf_counter() - start, len(tried))

    def _solve_fast(self, x: np.ndarray, u_p: np.ndarray | None) -> DecreaseResult:
        start = time.perf_counter()
        nu = self.system.nu
        u_p_in = np.zeros(nu) if u_p is None else np.asarray(u_p, float).reshape(nu)
        u_p_in = np.minimum(np.maximum(u_p_in, self._lb), self._ub)
        screened, h_x = self._screen(x, u_p_in)
        values = screened[self._index]
        h_proposal, h_x = float(values[1]), float(h_x[0])
        values = np.where(np.isfinite(values), values, np.inf)
        order = np.argsort(values, kind="stable")

        def cand(k: int) -> np.ndarray:
            return u_p_in if k == 1 else self._cand_static[k - (k > 1)]

        best_u, best_v = cand(order[0]).copy(), float(values[order[0]])
        sols, success, tried, kkt = [], False, [], 0
        for idx in order:
            if len(tried) >= self.n_local:
                break
            c = cand(idx)
            if any(np.allclose(c, t) for t in tried):
                continue
            tried.append(c)
            if self._kkt_start(x, c):
                kkt += 1
                success = True
                continue  # the local solver returns c itself; c is a screened candidate
            local = self._local(x, c)
            if isinstance(local, Solution):
                sols.append(local)
                if not local.usable:  # as the emitted C (BAL_SOLVED)
                    continue
                u_loc = np.asarray(local["u"], float).reshape(nu)
                if not (np.all(np.isfinite(u_loc)) and in_set(u_loc, self.U, 1e-7)):
                    continue
                v, ok = self.h_next(x, u_loc), local.success
            else:
                u_loc, v = local
                if not in_set(u_loc, self.U, 1e-7):
                    continue
                ok = True
            success = success or ok
            if v < best_v:
                best_u, best_v = u_loc.copy(), v
        return DecreaseResult(best_u, h_x, best_v, h_x - best_v, sols,
                              success or np.isfinite(best_v), u_p_in, h_proposal,
                              time.perf_counter() - start, len(tried), kkt)

    def _kkt_start(self, x: np.ndarray, c: np.ndarray) -> bool:
        """``c`` is a vertex of the box ``U`` where ``∇_u ĥ(f(x, u))`` points out of ``U``
        (first-order KKT conditions of (7.6) with multipliers ``∓∇``)."""
        if not self._box:
            return False
        at_ub, at_lb = c == self._ub, c == self._lb
        if not (at_ub | at_lb).all():
            return False
        g = self._grad(x, c)[0]
        return bool(((at_ub & (g <= 0.0)) | (at_lb & (g >= 0.0))).all())

    def _local(self, x: np.ndarray, c: np.ndarray
               ) -> tuple[np.ndarray, float] | Solution:
        """A local solve from ``c``: ``(u, value)`` from :class:`FastNLP`, or the
        compiled problem's :class:`Solution` (retry chain) when the fast solve fails."""
        out = self._fast_nlp.solve(self._fast_nlp.pack(x0=x), {"u": c})
        if out is not None:
            w, v = out
            u_loc = w[self._fast_nlp.offsets["u"]]
            if np.isfinite(u_loc).all() and np.isfinite(v):
                return u_loc, v
        return self.compiled.solve({"x0": x}, warm_start={"u": c})


def in_set(u: np.ndarray, U: Set, tol: float = 1e-9) -> bool:
    """``u ∈ U`` up to ``tol`` (a vectorized check for boxes, ``U.contains`` otherwise)."""
    u = np.asarray(u, float).reshape(-1)
    if isinstance(U, Box):
        return bool((u >= U.lb - tol).all() and (u <= U.ub + tol).all())
    return bool(U.contains(u, tol=tol))


def _project_box(u: np.ndarray, U: Set) -> np.ndarray:
    box = U if isinstance(U, Box) else U.bounding_box()
    return np.clip(np.asarray(u, float).reshape(-1), box.lb, box.ub)
