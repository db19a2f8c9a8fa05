"""The maximal decrease (7.6) of an explicit approximate PCBF ``ĥ`` by multi-start
(thesis Section 7.2, SPEC §2.28): the algorithm behind Algorithm 7.5.

``Δĥ(x) = ĥ(x) − min_{u ∈ U} ĥ(f(x, u))`` is a nonconvex NLP in ``u`` only (the formulation
:func:`~balustrade.problems.approximate.max_decrease_problem`). :class:`MaximalDecrease`
screens the starts ``Π_U(0)``, ``Π_U(u_p)`` and a coarse grid over ``U`` (SPEC §2.28
default) with one batched evaluation of ``ĥ(f(x, ·))`` and runs the compiled local solver
from the best ones. By Proposition 7.3 its minimizer is feasible in the filter (7.5) for
every ``ρ ∈ (0, 1]``.
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass

import casadi as ca
import numpy as np

from balustrade._checks import as_count
from balustrade.backends import Compiled, Solution, Target, compile, resolve_target
from balustrade.backends.casadi_fast import Buffered, FastNLP
from balustrade.dsl.sets import Box, Set
from balustrade.dsl.system import System
from balustrade.errors import BalustradeError
from balustrade.problems._args import check_system_sets
from balustrade.problems.approximate import HHat, as_h_function, max_decrease_problem


def local_target(target: Target | str | None, block: str) -> Target:
    """The CasADi target of the small (7.5)/(7.6) NLPs (default preset ``"exact"``)."""
    tgt = resolve_target(target, default="exact")
    if tgt.backend != "casadi":
        raise BalustradeError(f"{block}: target {tgt.name!r} is a {tgt.backend} target; the "
                              "(7.5)/(7.6) NLPs need a CasADi target")
    return tgt


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
    ``u_proposal = Π_U(u_p)`` (a screening candidate) with ``h_proposal =
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

    The candidates are projected onto ``U`` (:meth:`Set.project
    <balustrade.dsl.sets_base.Set.project>`; a clip for a box). The evaluation is made
    cheap (tests/test_approximate.py checks it against a plain reference that sends every
    local solve through ``Compiled.solve``):

    * one :class:`Buffered` call returns ``ĥ(f(x, c))`` for all candidates ``c`` (the
      static ones — ``Π_U(0)`` and the grid, exact duplicates removed — as constants)
      and ``ĥ(x)``;
    * a start that is already a first-order KKT point of (7.6) on a box ``U`` — a vertex
      of ``U`` where ``∇_u ĥ(f(x, u))`` points out of ``U`` in every component — is
      returned without calling the solver: from there an SQP method's QP step is zero and
      it stops at the start (an interior-point method to its tolerance); tested against the
      solver;
    * otherwise a :class:`FastNLP` solve, and the compiled problem's ``solve`` (with its
      retries) only when that fails.

    ``target`` (a :class:`~balustrade.backends.Target` or preset name, default
    ``"exact"``) compiles the local problem; it must be a CasADi target (the
    multi-start warm-starts ``u`` and calls the solver directly).
    """

    def __init__(self, system: System, U: Set, h_hat: HHat,
                 target: Target | str | None = None, grid_points: int = 5, n_local: int = 1):
        check_system_sets("MaximalDecrease", system, U=U)
        self.system, self.U = system, U
        self.h = as_h_function(h_hat, system.nx)
        self.target = local_target(target, "MaximalDecrease")
        self.ocp = max_decrease_problem(system, U, self.h)
        self.compiled: Compiled = compile(self.ocp, self.target)
        self.grid = coarse_grid(U, grid_points)
        self.n_local = as_count(n_local, "MaximalDecrease: n_local")
        nx, nu = system.nx, system.nu
        x, u = ca.SX.sym("x", nx), ca.SX.sym("u", nu)
        h_next = self.h(system(x, u))
        self._h_next = ca.Function("h_next", [x, u], [h_next])
        box = U if isinstance(U, Box) else U.bounding_box()
        self._lb, self._ub = np.asarray(box.lb, float), np.asarray(box.ub, float)
        self._box = isinstance(U, Box)
        self._u_zero = self._project(np.zeros(nu))
        # static candidates (Π_U(0), then the grid without exact duplicates), the dynamic
        # one (Π_U(u_p)) is an input; the full candidate list is [Π_U(0), Π_U(u_p), grid...]
        # and self._index maps it into the values vector
        static: list[np.ndarray] = []
        index = []
        for c in [self._u_zero, *self.grid]:
            hit = next((k for k, s in enumerate(static) if np.array_equal(s, c)), None)
            if hit is None:
                static.append(np.asarray(c, float))
                hit = len(static) - 1
            index.append(hit + 1)  # value 0 is Π_U(u_p)
        self._index = np.array([index[0], 0, *index[1:]], dtype=int)
        self._cand_static = np.vstack([self._u_zero.reshape(1, nu), self.grid])
        c1 = ca.SX.sym("c1", nu)
        values = [self._h_next(x, c1)] + [self._h_next(x, ca.DM(c)) for c in static]
        self._screen = Buffered(ca.Function("screen", [x, c1],
                                            [ca.vertcat(*values), self.h(x)]))
        self._h_next_buf = Buffered(self._h_next)
        self._h_buf = Buffered(ca.Function("h", [x], [self.h(x)]))
        self._grad = Buffered(ca.Function("h_next_grad", [x, u], [ca.gradient(h_next, u)]))
        # a local optimum of (7.6) is only a candidate (its value is evaluated again and
        # any point of U bounds the minimum): an acceptable stop needs no status check
        self._fast_nlp = FastNLP(self.compiled, check_stop=False)

    def _project(self, u: np.ndarray) -> np.ndarray:
        """``Π_U(u)``: a clip for a box, the exact projection otherwise."""
        if self._box:
            return np.minimum(np.maximum(u, self._lb), self._ub)
        return self.U.project(u)

    def h_value(self, x: np.ndarray) -> float:
        return float(self._h_buf(x)[0][0])

    def h_next(self, x: np.ndarray, u: np.ndarray) -> float:
        """``ĥ(f(x, u))`` (one evaluation: the certification test of Algorithm 7.5)."""
        return float(self._h_next_buf(x, u)[0][0])

    def solve(self, x: np.ndarray, u_p: np.ndarray | None = None) -> DecreaseResult:
        """(7.6) at ``x`` from the candidates ``Π_U(0)``, ``Π_U(u_p)`` and the grid."""
        start = time.perf_counter()
        x = np.asarray(x, float).reshape(-1)
        nu = self.system.nu
        u_p_in = np.zeros(nu) if u_p is None else np.asarray(u_p, float).reshape(nu)
        u_p_in = self._project(u_p_in)
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


__all__ = ["DecreaseResult", "MaximalDecrease", "coarse_grid", "in_set", "local_target"]
