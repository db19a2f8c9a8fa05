"""Horizon-free safety filters with an explicit approximate PCBF ``ĥ``.

* :class:`ApproximatePCBFFilter` — Algorithm 7.5: certify ``u_p`` by one evaluation
  (``u_p ∈ U`` and ``ĥ(f(x, u_p)) <= 0`` → apply ``u_p``); otherwise solve the maximal
  decrease (7.6) and the filter (7.5) and apply its minimizer.
* :class:`GridPCBFFilter` — Algorithm 8.7: evaluate ``ĥ(f(x, u_i))`` on a grid of inputs
  around ``u_{k−1}`` (rate limits ``|u_i − u_{k−1}| <= ū``), keep those meeting the
  multiplicative decrease ``ĥ(f(x, u_i)) <= ρ ĥ(x)`` and apply the one closest to ``u_p``
  (input-range-scaled norm), else the grid minimizer of ``ĥ(f(x, ·))``.

Neither raises in the loop (DESIGN.md principle 4). Fallbacks of Algorithm 7.5, recorded in
``StepInfo.fallback``: (7.5) fails → the (7.6) minimizer, feasible by Proposition 7.3
(``"max_decrease_solution"``; a (7.5) "solution" outside ``U`` is such a failure, status
``"filter_failed"`` whatever its solver's status, as in the C); every local (7.6) solve
fails → the best screened candidate of the multi-start grid (``"grid_minimizer"``); a
non-finite state → ``u_p`` projected on
``U`` (status ``"non_finite_state"``, ``"projected_proposal"``). A (7.5) solve that ends
merely ``feasible`` (not converged, primal feasible) is applied: it lies in ``U`` and meets
the decrease of (7.5), so it is safe, only possibly not the closest input to ``u_p``
(status ``"filter_feasible"``, flagged in ``StepInfo.uncertified``); likewise a feasible
local (7.6) point is a valid candidate of the maximal decrease (any ``u ∈ U`` bounds it).
NaN or inf entries of ``u_p`` are read as 0 and the step runs as usual (status
``"non_finite_proposal[_<status>]"``, :func:`~balustrade.control.fallbacks.finite_proposal`).
The emitted C step (:func:`balustrade.codegen.emit_approximate`) takes the same decisions.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable

import casadi as ca
import numpy as np

from balustrade._checks import as_count, as_float_array, as_scalar, as_vector, check_instance
from balustrade.backends import Compiled, Solution, Target, compile
from balustrade.backends.casadi_fast import Buffered, FastNLP
from balustrade.control.base import StepInfo, note_solve
from balustrade.control.decrease import DecreaseResult, MaximalDecrease, in_set, local_target
from balustrade.control.deploy import ApproximateDeployment, GridDeployment
from balustrade.control.fallbacks import (
    finite_proposal,
    finite_state,
    note_proposal,
    project,
    projected_proposal,
)
from balustrade.dsl.sets import Box, Set
from balustrade.dsl.system import System
from balustrade.errors import BalustradeError
from balustrade.problems.approximate import (
    HHat,
    approximate_filter_problem,
    as_h_function,
    decrease_bound,
)


class ApproximatePCBFFilter:
    """Algorithm 7.5 with ``ρ ∈ (0, 1]`` (``ρ = 1``: maximal decrease of ``ĥ`` each step).

    ``certify=False`` disables the shortcut of line 4 (every step solves (7.6) and (7.5)).
    Counters: ``n_steps``, ``n_certified`` (shortcut fired), ``n_solved`` ((7.6) solved),
    ``n_proposal_feasible`` (after (7.6), ``u_p`` itself met the decrease of (7.5), so it
    is the minimizer and (7.5) is not solved; ``exact_shortcut=False`` always solves
    (7.5)), ``n_fallbacks``.

    The step runs with buffered CasADi evaluations, the KKT-vertex start of (7.6) and
    :class:`~balustrade.backends.casadi_fast.FastNLP` first attempts (see
    :class:`~balustrade.control.decrease.MaximalDecrease`); a failed attempt goes through
    ``Compiled.solve`` and its retries, so statuses and fallbacks are those of a plain
    implementation (tests/test_approximate.py holds that reference and compares).
    ``target`` (a CasADi target or preset, default ``"exact"``) compiles (7.5) and
    (7.6). ``StepInfo.solve_time`` is the wall time of (7.6) and
    (7.5) including screening; ``StepInfo.solutions`` holds the :class:`Solution` objects
    of solves that went through ``Compiled.solve`` (none on the fast path).

    ``network`` (optional): the network ``ĥ`` was exported from
    (:class:`~balustrade.learn.train.MLPModel`, ``h_hat = to_casadi(network)``), checked
    to equal ``h_hat`` on a few states. The Python step does not use it; the emitted C
    (:func:`~balustrade.codegen.emit_approximate`) then evaluates ``ĥ`` as loops over the
    weights (the same operations, a few kB of code instead of ~100 kB: several times faster
    when the caches are cold, docs/obstacles.md).
    """

    def __init__(self, system: System, U: Set, h_hat: HHat, rho: float = 1.0,
                 target: Target | str | None = None, certify: bool = True,
                 grid_points: int = 5, n_local: int = 1, eps: float = 1e-6,
                 exact_shortcut: bool = True, network: object | None = None):
        check_instance(system, System, "ApproximatePCBFFilter: system")
        check_instance(U, Set, "ApproximatePCBFFilter: U")
        rho = as_scalar(rho, "ApproximatePCBFFilter: rho", 0.0, 1.0, low_open=True)
        eps = as_scalar(eps, "ApproximatePCBFFilter: eps", 0.0)
        as_count(grid_points, "ApproximatePCBFFilter: grid_points", 1)
        as_count(n_local, "ApproximatePCBFFilter: n_local", 1)
        self.system, self.U, self.rho, self.certify = system, U, rho, bool(certify)
        self.exact_shortcut = bool(exact_shortcut)
        self.nu = system.nu
        self.h = as_h_function(h_hat, system.nx)
        self.network = None if network is None else _checked_network(network, self.h,
                                                                     system.nx)
        self.target = local_target(target, "ApproximatePCBFFilter")
        self.decrease = MaximalDecrease(system, U, self.h, self.target, grid_points, n_local)
        self.filter: Compiled = compile(approximate_filter_problem(system, U, self.h, eps),
                                        self.target)
        self._h_next = self.decrease._h_next
        self._fast_filter = FastNLP(self.filter)
        self.reset()

    def reset(self) -> None:
        self.n_steps = self.n_certified = self.n_solved = self.n_fallbacks = 0
        self.n_proposal_feasible = 0

    def certifies(self, x: np.ndarray, u_p: np.ndarray) -> bool:
        """Line 4 of Algorithm 7.5: ``u_p ∈ U`` and ``ĥ(f(x, u_p)) <= 0``."""
        return in_set(u_p, self.U) and self.decrease.h_next(x, u_p) <= 0.0

    def step(self, x: np.ndarray, u_p: np.ndarray) -> tuple[np.ndarray, StepInfo]:
        """One step of Algorithm 7.5 (module docstring). Wrong shapes or types raise a
        :class:`~balustrade.errors.BalustradeError`; NaN or inf values never do."""
        u_p, replaced = finite_proposal(u_p, self.nu, "ApproximatePCBFFilter.step: u_p")
        x = finite_state(x, self.system.nx, "ApproximatePCBFFilter.step: x")
        self.n_steps += 1
        if x is None:
            self.n_fallbacks += 1
            return projected_proposal(u_p, self.U)
        u, info = self._step(x, u_p)
        return u, note_proposal(info, replaced)

    def _step(self, x: np.ndarray, u_p: np.ndarray) -> tuple[np.ndarray, StepInfo]:
        start = time.perf_counter()
        if self.certify and self.certifies(x, u_p):
            self.n_certified += 1
            info = StepInfo(status="certified", solve_time=time.perf_counter() - start)
            info.values.update(certified=1.0)
            return u_p.copy(), info
        try:
            return self._solve(x, u_p)
        except Exception as exc:  # noqa: BLE001 - never raise in the loop (principle 4)
            self.n_fallbacks += 1
            return project(u_p, self.U), StepInfo(status=f"error: {exc}",
                                                  fallback="projected_proposal")

    def _solve(self, x: np.ndarray, u_p: np.ndarray) -> tuple[np.ndarray, StepInfo]:
        self.n_solved += 1
        start = time.perf_counter()
        dec = self.decrease.solve(x, u_p)
        info = StepInfo(solutions={"max_decrease": dec.solutions})
        info.values.update(certified=0.0, h_hat=dec.h_x, dh=dec.dh)
        if not dec.success:
            info.status, info.fallback = "max_decrease_failed", "grid_minimizer"
            self.n_fallbacks += 1
            info.solve_time = time.perf_counter() - start
            return dec.u.copy(), info
        if self.exact_shortcut and in_set(u_p, self.U):
            # ĥ(f(x, u_p)): u_p is the screening candidate Π_U(u_p) unless it lies
            # within the 1e-9 tolerance outside U
            h_up = dec.h_proposal if (dec.u_proposal == u_p).all() \
                else self.decrease.h_next(x, u_p)
            if h_up - dec.h_x <= decrease_bound(dec.dh, self.rho):
                # u_p is feasible in (7.5), where the cost is 0: it is the minimizer (exact)
                self.n_proposal_feasible += 1
                info.status = "proposal_feasible"
                info.solve_time = time.perf_counter() - start
                return u_p.copy(), info
        u, status = self._filter(x, u_p, dec, info)
        info.solve_time = time.perf_counter() - start
        if u is not None and in_set(u, self.U, 1e-7):
            # a merely feasible (7.5) point meets the decrease in U: safe, flagged
            info.status = "ok" if note_solve(info, "filter", status) else f"filter_{status}"
            return u, info
        # (7.5) gave no input, or one outside U: that is no solution of (7.5), whatever the
        # solver said (its constraint u ∈ U fails), so the status never reads "optimal"
        # ("filter_failed", as the C's BAL_APPROX_MAX_DECREASE); Proposition 7.3's fallback
        info.status = f"filter_{status}" if u is None else "filter_failed"
        info.fallback = "max_decrease_solution"
        self.n_fallbacks += 1
        return dec.u.copy(), info

    def _filter(self, x: np.ndarray, u_p: np.ndarray, dec: DecreaseResult,
                info: StepInfo) -> tuple[np.ndarray | None, str]:
        """(7.5) warm-started at the (7.6) minimizer: a :class:`FastNLP` solve (same
        problem and options, cold multipliers), the compiled problem's ``solve`` (with
        its retries) if that fails. Returns the minimizer, or the feasible point of a
        solve that did not converge (``None`` if not even that), and the solution status."""
        fast = self._fast_filter
        out = fast.solve(fast.pack(x0=x, u_p=u_p, dh=dec.dh, rho=self.rho), {"u": dec.u})
        if out is not None:
            u = out[0][fast.offsets["u"]].copy()
            if np.isfinite(u).all():
                return u, "optimal"
        return self._filter_solve(x, u_p, dec, info)

    def _filter_solve(self, x: np.ndarray, u_p: np.ndarray, dec: DecreaseResult,
                      info: StepInfo) -> tuple[np.ndarray | None, str]:
        """(7.5) through the compiled problem's ``solve`` (with its retries)."""
        sol = self.filter.solve({"x0": x, "u_p": u_p, "dh": dec.dh, "rho": self.rho},
                                warm_start={"u": dec.u})
        info.solutions["filter"] = sol
        u = np.asarray(sol["u"], float).reshape(self.nu) if sol.usable else None
        return u, sol.status

    def deployment_spec(self) -> ApproximateDeployment:
        """What the emitted C step needs (:func:`balustrade.codegen.emit_approximate`):
        (7.6) and (7.5) compiled, ``U``, the model, ``ĥ``, the screening grid and the
        constants of Algorithm 7.5."""
        dec = self.decrease
        return ApproximateDeployment(
            decrease=dec.compiled, filter=self.filter, U=self.U, system=self.system,
            h=self.h, grid=np.atleast_2d(np.asarray(dec.grid, dtype=float)),
            n_local=int(dec.n_local), rho=float(self.rho), certify=bool(self.certify),
            exact_shortcut=bool(self.exact_shortcut), network=self.network)


#: Algorithm 8.7: the most candidate inputs per step (each one ``ĥ(f(x, u))`` evaluation);
#: the thesis' grid has 55
MAX_GRID_POINTS = 1_000_000


class GridPCBFFilter:
    """Algorithm 8.7 (SPEC §2.34): the input-grid approximate PCBF filter with rate limits.

    ``half_width`` ``ū`` and ``spacing`` ``Δu`` (per input) define the offsets
    ``j·Δu``, ``|j·Δu| <= ū``, around the last applied input ``u_{k−1}``; candidates are
    clipped to ``U`` (a box) or dropped if outside ``U``. ``ĥ(f(x, u_i))`` is evaluated for
    all candidates in one batched CasADi call. ``ρ`` multiplies ``ĥ`` (default 0.9).

    ``h_rows`` (optional): the same ``ĥ`` on the rows of an ``(M, nx)`` array, returning
    ``(M,)`` values (e.g. a numpy network, :meth:`~balustrade.learn.train.MLPModel.__call__`).
    The step then computes ``f(x, u_i)`` in one mapped CasADi call and ``ĥ`` with
    ``h_rows``: a large network evaluated as dense matrix products instead of scalar
    CasADi operations (≈ 10× faster for 55 candidates of a 4 × 32 net). It must equal
    ``h_hat`` (checked on a few states at construction); the emitted C uses ``h_hat``.
    """

    def __init__(self, system: System, U: Set, h_hat: HHat, half_width: object,
                 spacing: object, rho: float = 0.9, u_init: np.ndarray | None = None,
                 h_rows: Callable[[np.ndarray], np.ndarray] | None = None):
        check_instance(system, System, "GridPCBFFilter: system")
        check_instance(U, Set, "GridPCBFFilter: U")
        self.system, self.U = system, U
        self.rho = as_scalar(rho, "GridPCBFFilter: rho", 0.0, 1.0, low_open=True)
        self.nu = system.nu
        self.half_width = as_vector(half_width, "GridPCBFFilter: half_width", self.nu)
        self.spacing = as_vector(spacing, "GridPCBFFilter: spacing", self.nu)
        if np.any(self.spacing <= 0) or np.any(self.half_width < 0):
            raise BalustradeError("GridPCBFFilter: spacing must be positive and half_width "
                                  "nonnegative")
        if not (np.all(np.isfinite(self.half_width)) and np.all(np.isfinite(self.spacing))):
            raise BalustradeError("GridPCBFFilter: half_width and spacing must be finite")
        counts = 2 * np.floor(self.half_width / self.spacing + 1e-9) + 1
        if float(np.prod(counts)) > MAX_GRID_POINTS:
            raise BalustradeError(f"GridPCBFFilter: half_width {self.half_width} and spacing "
                                  f"{self.spacing} give {float(np.prod(counts)):.3g} candidate "
                                  f"inputs per step (at most {MAX_GRID_POINTS:g}); widen the "
                                  "spacing")
        axes = [np.arange(-np.floor(w / s + 1e-9), np.floor(w / s + 1e-9) + 1) * s
                for w, s in zip(self.half_width, self.spacing)]
        self.offsets = np.array(list(itertools.product(*axes)), dtype=float)
        box = U if isinstance(U, Box) else U.bounding_box()
        span = np.asarray(box.ub, float) - np.asarray(box.lb, float)
        self.scale = np.where(np.isfinite(span) & (span > 0), span, 1.0)
        self.h = as_h_function(h_hat, system.nx)
        x, u = ca.SX.sym("x", system.nx), ca.SX.sym("u", system.nu)
        self._h_next = ca.Function("h_next", [x, u], [self.h(system(x, u))])
        self._many = self._h_next.map(len(self.offsets))
        self._many_buf = Buffered(self._many)  # one low-overhead call per step
        self._h_buf = Buffered(self.h)
        self.h_rows = None if h_rows is None else _checked_rows(h_rows, self.h, system.nx)
        if self.h_rows is not None:
            f = ca.Function("f", [x, u], [system(x, u)])
            self._next_buf = Buffered(f.map(len(self.offsets)))
        self.u_init = np.zeros(self.nu) if u_init is None else \
            as_vector(u_init, "GridPCBFFilter: u_init", self.nu)
        self.reset()

    def reset(self) -> None:
        self.u_prev = project(self.u_init, self.U)
        self.n_steps = self.n_decrease_infeasible = 0

    def candidates(self) -> np.ndarray:
        """The candidate set ``C`` of Algorithm 8.7 (rows), around ``u_{k−1}``."""
        cand = self.u_prev.reshape(1, -1) + self.offsets
        if isinstance(self.U, Box):
            cand = np.clip(cand, self.U.lb, self.U.ub)
        else:
            cand = cand[self.U.contains_many(cand)]
            if len(cand) == 0:
                cand = project(self.u_prev, self.U).reshape(1, -1)
        return np.unique(np.round(cand, 12), axis=0)

    def step(self, x: np.ndarray, u_p: np.ndarray) -> tuple[np.ndarray, StepInfo]:
        self.n_steps += 1
        start = time.perf_counter()
        u_p, replaced = finite_proposal(u_p, self.nu, "GridPCBFFilter.step: u_p")
        x = finite_state(x, self.system.nx, "GridPCBFFilter.step: x")
        if x is None:  # keep the last input (Algorithm 8.7 is rate-limited around it)
            return self.u_prev.copy(), StepInfo(status="non_finite_state",
                                                fallback="previous_input")
        u, info = self._step(x, u_p, start)
        return u, note_proposal(info, replaced)

    def _step(self, x: np.ndarray, u_p: np.ndarray, start: float
              ) -> tuple[np.ndarray, StepInfo]:
        cand = self.candidates()
        padded = np.vstack([cand, np.repeat(cand[-1:], len(self.offsets) - len(cand), 0)])
        n = len(self.offsets)
        if self.h_rows is None:
            values = self._many_buf(np.tile(x, n), padded.reshape(-1))[0][: len(cand)]
        else:  # f(x, u_i) in one mapped call (column-major: one state per column)
            nxt = self._next_buf(np.tile(x, n), padded.reshape(-1))[0]
            values = np.asarray(self.h_rows(nxt.reshape(n, -1)[: len(cand)]), float)
        values = np.where(np.isfinite(values), values, np.inf)
        h_x = float(self._h_buf(x)[0][0])
        ok = values <= self.rho * h_x
        info = StepInfo(values={"h_hat": h_x, "n_candidates": float(len(cand))})
        if not np.any(ok):
            self.n_decrease_infeasible += 1
            u = cand[int(np.argmin(values))]
            info.status, info.fallback = "no_decreasing_candidate", "grid_minimizer"
        else:
            dist = np.sum(((cand[ok] - u_p) / self.scale) ** 2, axis=1)
            u = cand[ok][int(np.argmin(dist))]
            info.status = "ok"
        info.solve_time = time.perf_counter() - start
        self.u_prev = u.copy()
        return u.copy(), info

    def deployment_spec(self) -> GridDeployment:
        """What the emitted C step needs (:func:`balustrade.codegen.emit_grid`): the model,
        ``U``, ``ĥ``, the offsets, the distance scale, ``ρ`` and ``u_init``."""
        return GridDeployment(system=self.system, U=self.U, h=self.h,
                              offsets=self.offsets.copy(), scale=self.scale.copy(),
                              rho=float(self.rho), u_init=self.u_init.copy())


def _checked_network(network: object, h: ca.Function, nx: int) -> object:
    """``network`` if it has the attributes of an MLP (``weights``, ``biases``, ``mean``,
    ``scale``, ``output_transform``), takes ``nx`` inputs and equals ``h`` on a few fixed
    states (its own evaluation, relative 1e-9), else a BalustradeError naming the argument."""
    missing = [a for a in ("weights", "biases", "mean", "scale", "output_transform")
               if not hasattr(network, a)]
    if missing or not callable(network):
        raise BalustradeError(f"ApproximatePCBFFilter: network must be the MLP h_hat was "
                              f"exported from (balustrade.learn.train.MLPModel); "
                              f"{type(network).__name__} lacks {missing or ['__call__']}")
    shapes = [np.shape(W) for W in network.weights]
    if not shapes or len(shapes[0]) != 2 or shapes[0][1] != nx or shapes[-1][0] != 1:
        raise BalustradeError(f"ApproximatePCBFFilter: network must map {nx} states to one "
                              f"value; its weight shapes are {shapes}")
    X = np.random.default_rng(1).uniform(-1.0, 1.0, (4, nx))
    want = np.array([float(h(x)) for x in X])
    got = np.asarray(network(X), float).reshape(-1)
    if got.shape != want.shape or not np.allclose(got, want, rtol=1e-9, atol=1e-12):
        raise BalustradeError(f"ApproximatePCBFFilter: network must be the MLP h_hat was "
                              f"exported from; on 4 test states it gave {got} where h_hat "
                              f"gives {want}")
    return network


def _checked_rows(h_rows: object, h: ca.Function, nx: int
                  ) -> Callable[[np.ndarray], np.ndarray]:
    """``h_rows`` if it is callable and equals ``h`` on a few fixed states (relative 1e-9),
    else a BalustradeError naming the argument."""
    if not callable(h_rows):
        raise BalustradeError(f"GridPCBFFilter: h_rows must be callable, got "
                              f"{type(h_rows).__name__}")
    X = np.random.default_rng(0).uniform(-1.0, 1.0, (4, nx))
    want = np.array([float(h(x)) for x in X])
    try:
        out = h_rows(X)
    except Exception as exc:  # noqa: BLE001 — any failure of the user's callable
        raise BalustradeError(f"GridPCBFFilter: h_rows failed on a (4, {nx}) array of test "
                              f"states ({type(exc).__name__}: {exc}); it must map the rows "
                              f"of an (M, {nx}) array to (M,) values of h_hat") from exc
    got = as_float_array(out, "GridPCBFFilter: h_rows(X) (values of h_hat)").reshape(-1)
    if got.shape != want.shape or not np.allclose(got, want, rtol=1e-9, atol=1e-12,
                                                         equal_nan=True):
        raise BalustradeError(f"GridPCBFFilter: h_rows must equal h_hat on the rows of an "
                              f"(M, {nx}) array and return (M,) values; on 4 test states "
                              f"it gave shape {got.shape} and values {got} instead of {want}")
    return h_rows


__all__ = ["ApproximatePCBFFilter", "GridPCBFFilter", "Solution"]
