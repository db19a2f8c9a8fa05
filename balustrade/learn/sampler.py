"""Sampling the (extended) PCBF for learning: Algorithm 7.6 and plain gridding (Section 7.5).

At a state ``x`` the extended PCBF (7.7) is ``h(x) = h_PB(x)`` (2.24) outside ``S_PB`` and
``c_h · h̄_PB(x)`` (7.8) on ``S_PB``; ``h_PB = max(0, h)``. Algorithm 7.6 walks lines from a
seed towards goal points in steps of ``d`` and, at each point, solves only the problem that
the in-``S_PB`` flag of the previous point suggests, warm-started with the previous primal
AND dual solution of the same problem (a :class:`~balustrade.backends.Solution` passed as
``warm_start`` to the CasADi-compiled problem):

* previously in ``S_PB``: solve (7.8); if ``h̄_PB > tol`` (SPEC §2.30 reading of
  "infeasible"), leave ``S_PB`` and solve (2.24);
* previously outside: solve (2.24); if ``h_PB <= tol``, enter ``S_PB`` and solve (7.8).

``tol = 1e-6`` (SPEC default). A point where a solve fails (e.g. (2.24) infeasible: with a
hard terminal constraint, SPEC §2.32, there are states from which no input sequence meets
it) is kept as a row with ``ok = False`` and the failing solve's status in the ``reason``
column (empty for good rows); training drops these rows
(:meth:`~balustrade.learn.dataset.ShardedDataset.arrays`) and the walk of that line stops.
Plain gridding (Section 7.5) walks the grid in snake order with the same warm starts and
rejects points with ``h_PB`` above a cap.

The compiled problems are not shipped to workers: a :class:`ProblemSpec` (a factory name
and JSON-able arguments) is, and each worker process builds and caches the problems once.
"""

from __future__ import annotations

import importlib
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from balustrade.backends import Compiled, Solution, Status, Target, compile, sampling_targets
from balustrade.dsl.sets import Box
from balustrade.errors import BalustradeError, moved_names

TOL = 1e-6
COLUMNS = ("h", "h_pb", "h_bar", "in_s", "ok", "iterations", "reason")


@dataclass
class PCBFProblems:
    """The compiled problems a sampler needs: (2.24) (parameter ``x0``, objective
    ``h_PB``), (7.8) (parameter ``x0``, objective ``h̄_PB``), the state box ``X`` used for
    goal points and the scale ``c_h`` of (7.9). ``slack_cold``/``extended_cold`` (optional)
    are the same problems compiled with options for cold starts, used when no warm start
    exists (an interior-point method wants different settings for the two cases)."""

    slack: Compiled
    extended: Compiled
    X: Box
    c_h: float = 1.0
    slack_cold: Compiled | None = None
    extended_cold: Compiled | None = None
    #: optional ``x ↦ {variable: primal guess}`` for (2.24): where the solve the walk makes
    #: ends with ``h_PB > tol`` (or fails), (2.24) is solved once more from this guess and
    #: its value replaces the walk's if it is ``optimal`` and lower (both are then values
    #: of feasible points, so the lower one is nearer the minimum of the nonconvex (2.24));
    #: :func:`balustrade.examples.obstacles.obstacle_problems` gives a braking trajectory
    slack_guess: Callable[[np.ndarray], dict] | None = None

    @property
    def nx(self) -> int:
        return self.X.dim


def compile_pair(ocp: object, target: Target | str) -> tuple[Compiled, Compiled | None]:
    """Compile ``ocp`` for warm-started solves and a twin for cold starts, on the targets
    :func:`~balustrade.backends.sampling_targets` gives for ``target``:

    * ``"fast-sqp"`` (default of :func:`~balustrade.examples.pendulum.pendulum_problems`):
      warm solves by the fast SQP from the previous primal-dual solution, with no retry
      chain (``fast-sqp-noretry``) — a warm solve that does not converge is redone from
      scratch by the cold twin
      (``sampling-cold``: an interior-point target demanding absolute complementarity),
      which also does every cold start (first point of a path, first point after a switch
      between (2.24) and (7.8));
    * ``"exact"``: the interior-point target for both, the warm twin with its warm-start
      options (``sampling-warm``);
    * any other target: one compiled problem, no twin.
    """
    warm, cold = sampling_targets(target)
    return compile(ocp, warm), None if cold is None else compile(ocp, cold)


#: sampling problems by name: ``"package.module:function"`` paths returning
#: :class:`PCBFProblems` (the examples live outside :mod:`balustrade.learn`, which defines no
#: model; :func:`balustrade.examples.pendulum.pendulum_problems` is the pendulum of Section 7.5,
#: :func:`balustrade.examples.obstacles.obstacle_problems` the obstacle car of Section 8.3,
#: :func:`balustrade.examples.chronos.chronos_problems` the Chronos car of Section 8.4)
PROBLEMS: dict[str, str] = {"pendulum": "balustrade.examples.pendulum:pendulum_problems",
                            "obstacles": "balustrade.examples.obstacles:obstacle_problems",
                            "chronos": "balustrade.examples.chronos:chronos_problems"}


@dataclass(frozen=True)
class ProblemSpec:
    """What to sample, in picklable form: ``factory`` is a name of :data:`PROBLEMS` or
    ``"package.module:function"`` returning :class:`PCBFProblems`; ``kwargs`` its arguments."""

    factory: str = "pendulum"
    kwargs: tuple[tuple[str, object], ...] = ()

    @classmethod
    def of(cls, factory: str = "pendulum", **kwargs: object) -> ProblemSpec:
        return cls(factory, tuple(sorted(kwargs.items())))

    def to_dict(self) -> dict:
        return {"factory": self.factory, "kwargs": dict(self.kwargs)}

    def build(self) -> PCBFProblems:
        """Build (once per process) the compiled problems."""
        key = (self.factory, self.kwargs)
        if key not in _CACHE:
            path = PROBLEMS.get(self.factory, self.factory)
            if ":" in path:
                module, name = path.split(":", 1)
                fn = getattr(importlib.import_module(module), name)
            else:
                raise BalustradeError(f"unknown sampling problem {self.factory!r}; use one of "
                                      f"{sorted(PROBLEMS)} or 'package.module:function'")
            _CACHE[key] = fn(**dict(self.kwargs))
        return _CACHE[key]


_CACHE: dict[tuple, PCBFProblems] = {}


@dataclass
class Seed:
    """A seed ``s = (x, o, in_S)`` of Algorithm 7.6: the state, the last primal-dual
    solutions of (2.24) and (7.8) (the warm starts ``o``) and the in-``S_PB`` flag."""

    x: np.ndarray
    in_s: bool = False
    slack: Solution | None = None
    extended: Solution | None = None


@dataclass
class Sample:
    x: np.ndarray
    h: float
    h_pb: float
    h_bar: float
    in_s: bool
    ok: bool
    iterations: int = 0
    solutions: dict = field(default_factory=dict, repr=False)
    reason: str = ""


class Evaluator:
    """Lines 11–30 of Algorithm 7.6 at one point, with or without warm starts."""

    def __init__(self, problems: PCBFProblems, tol: float = TOL, warm: bool = True):
        self.p, self.tol, self.warm = problems, float(tol), bool(warm)

    def _solve(self, which: str, x: np.ndarray, seed: Seed) -> Solution:
        warm: Solution | None = None
        if self.warm:
            same = seed.slack if which == "slack" else seed.extended
            if same is not None and same.success:
                warm = same  # primal and dual of the same problem
        if warm is None:
            return self._cold_solve(which, x, seed)
        prob = self.p.slack if which == "slack" else self.p.extended
        if getattr(prob, "solver_name", warm.solver) != warm.solver:
            # a solution of the cold twin (another solver, e.g. an interior point): its
            # multipliers are small but nonzero on inactive rows, which the fast SQP's
            # active-set QP reads as a bad active-set guess (up to 1 s per solve measured);
            # pass the primal point only
            warm = dict(warm.primal)
        sol = prob.solve({"x0": x}, warm_start=warm)
        if not sol.success:  # a bad warm start: retry from scratch
            seed_cold = Seed(x)
            retry = self._cold_solve(which, x, seed_cold)
            retry.iterations += sol.iterations
            return retry
        return sol

    def _slack(self, x: np.ndarray, seed: Seed) -> Solution:
        """(2.24) as the walk solves it, then, if that did not place ``x`` in ``S_PB`` and
        the problems have a ``slack_guess``, once more from the guess; the lower converged
        value wins (audit D, session 15: warm- and cold-started solves of the obstacle car
        ended ``optimal`` at ``h_PB`` up to 0.08 where a stop with zero slack exists). The
        retry counts only when it is ``optimal``: an acceptable-level stop may violate rows,
        and taking the lower value would favour it in the unsafe direction (review R3)."""
        s = self._solve("slack", x, seed)
        guess = self.p.slack_guess
        if guess is None or (s.success and max(float(s.objective), 0.0) <= self.tol):
            return s
        g = self.p.slack.solve({"x0": x}, warm_start=guess(x))
        better = g.status == Status.OPTIMAL and (not s.success
                                                 or float(g.objective) < float(s.objective))
        keep, other = (g, s) if better else (s, g)
        keep.iterations += other.iterations
        return keep

    def _cold_solve(self, which: str, x: np.ndarray, seed: Seed) -> Solution:
        cold = self.p.slack_cold if which == "slack" else self.p.extended_cold
        if cold is None:
            cold = self.p.slack if which == "slack" else self.p.extended
        return cold.solve({"x0": x})

    def point(self, x: np.ndarray, seed: Seed) -> tuple[Sample, Seed]:
        x = np.asarray(x, dtype=float).reshape(-1)
        new = Seed(x, seed.in_s, seed.slack, seed.extended)
        its, sols = 0, {}
        h_pb = h_bar = math.nan
        ok = True
        if seed.in_s:
            e = self._solve("extended", x, seed)
            its, sols["extended"] = its + e.iterations, e
            ok = e.success
            h_bar = float(e.objective)
            new.extended = e if e.success else None
            if e.success and h_bar <= self.tol:
                in_s, h_pb = True, 0.0
            else:
                s = self._slack(x, seed)
                its, sols["slack"] = its + s.iterations, s
                ok = s.success
                new.slack = s if s.success else None
                h_pb, in_s = max(float(s.objective), 0.0), False
                if s.success and h_pb <= self.tol:  # (7.8) failed but x ∈ S_PB after all
                    in_s = True
        else:
            s = self._slack(x, seed)
            its, sols["slack"] = its + s.iterations, s
            ok = s.success
            new.slack = s if s.success else None
            h_pb = max(float(s.objective), 0.0)
            in_s = bool(s.success and h_pb <= self.tol)
            if in_s:
                e = self._solve("extended", x, new)
                its, sols["extended"] = its + e.iterations, e
                ok = e.success
                new.extended = e if e.success else None
                h_bar = float(e.objective)
        if in_s:
            h_pb = 0.0
            # the label on S_PB is c_h·h̄_PB (7.9): only from a converged (7.8); the
            # objective of a failed one (e.g. (7.8) failed, then (2.24) placed x in S_PB)
            # is no value of h̄_PB, and the row is dropped (audit B, session 14)
            e = sols.get("extended")
            if e is None or not e.success:
                ok, h_bar = False, math.nan
            h = self.p.c_h * min(h_bar, 0.0) if np.isfinite(h_bar) else math.nan
        else:
            h = h_pb
        new.in_s = in_s
        good = bool(ok and np.isfinite(h))
        reason = "" if good else _reason(sols)
        return Sample(x, h, h_pb, h_bar, in_s, good, its, sols, reason), new

    def walk(self, x0: np.ndarray, goal: np.ndarray, d: float, seed: Seed,
             cap: float | None = None) -> tuple[list[Sample], Seed]:
        """One line of Algorithm 7.6 (lines 8–32): ``n = ⌈‖x0 − g‖ / d⌉`` points
        ``x_i = x0 + i (g − x0) / n``; stops early when ``h > cap`` or a solve fails."""
        x0, goal = np.asarray(x0, float), np.asarray(goal, float)
        n = max(1, int(math.ceil(np.linalg.norm(goal - x0) / d)))
        out: list[Sample] = []
        for i in range(1, n + 1):
            sample, seed = self.point(x0 + i * (goal - x0) / n, seed)
            out.append(sample)
            if not sample.ok or (cap is not None and sample.h > cap):
                break
        return out, seed

    def path(self, points: np.ndarray, chain_distance: float = np.inf) -> list[Sample]:
        """Evaluate points in order, warm-starting each from the previous one when they are
        closer than ``chain_distance`` (a cold start otherwise)."""
        seed: Seed | None = None
        out = []
        for x in np.asarray(points, float):
            if seed is None or np.linalg.norm(x - seed.x) > chain_distance:
                seed = Seed(x)
            sample, seed = self.point(x, seed)
            out.append(sample)
        return out


# -- work units --------------------------------------------------------------------------
@dataclass(frozen=True)
class Chunk:
    """A unit of sampling work with a deterministic result.

    ``kind="grid"``: evaluate ``points`` in order (warm-started), keep rows with
    ``h_PB <= cap``. ``kind="geometric"``: Algorithm 7.6 over the goal points ``points``
    from the initial seed ``x_seed``, seeds drawn with ``numpy.random.default_rng(seed)``.
    """

    id: int
    kind: str
    points: np.ndarray
    seed: int = 0
    step: float = 0.01
    cap: float | None = None
    x_seed: tuple[float, ...] | None = None
    chain_distance: float = np.inf
    warm: bool = True

    def __len__(self) -> int:
        return len(self.points)


def _reason(sols: dict) -> str:
    """Why a point was dropped: ``"<problem>: <status>"`` of the failed solves (the last
    one decides), ``"non-finite value"`` if every solve succeeded."""
    failed = [f"{k}: {v.status}" for k, v in sols.items() if not v.success]
    return "; ".join(failed) if failed else "non-finite value"


def run_chunk(spec: ProblemSpec, chunk: Chunk, tol: float = TOL) -> dict[str, np.ndarray]:
    """Run one chunk in this process; returns columns ``x0..x{n-1}``, :data:`COLUMNS`,
    ``chunk`` and ``index`` (row order within the chunk)."""
    problems = spec.build()
    ev = Evaluator(problems, tol, warm=chunk.warm)
    samples: list[Sample] = []
    if chunk.kind == "grid":
        samples = [s for s in ev.path(chunk.points, chunk.chain_distance)
                   if chunk.cap is None or (s.ok and s.h_pb <= chunk.cap)]
    elif chunk.kind == "geometric":
        rng = np.random.default_rng(chunk.seed)
        x_seed = np.zeros(problems.nx) if chunk.x_seed is None else np.asarray(chunk.x_seed)
        first, seed = ev.point(x_seed, Seed(x_seed))
        seeds, samples = [seed], [first]
        for goal in chunk.points:
            start = seeds[int(rng.integers(len(seeds)))]
            line, end = ev.walk(start.x, goal, chunk.step, start, chunk.cap)
            samples.extend(line)
            if line and line[-1].ok:
                seeds.append(end)
    else:
        raise BalustradeError(f"unknown chunk kind {chunk.kind!r} (use 'grid' or 'geometric')")
    return samples_to_columns(samples, problems.nx, chunk.id)


def samples_to_columns(samples: list[Sample], nx: int, chunk_id: int = 0
                       ) -> dict[str, np.ndarray]:
    cols: dict[str, np.ndarray] = {}
    X = np.array([s.x for s in samples], dtype=float).reshape(len(samples), nx)
    for j in range(nx):
        cols[f"x{j}"] = X[:, j]
    cols["h"] = np.array([s.h for s in samples], dtype=float)
    cols["h_pb"] = np.array([s.h_pb for s in samples], dtype=float)
    cols["h_bar"] = np.array([s.h_bar for s in samples], dtype=float)
    cols["in_s"] = np.array([s.in_s for s in samples], dtype=bool)
    cols["ok"] = np.array([s.ok for s in samples], dtype=bool)
    cols["iterations"] = np.array([s.iterations for s in samples], dtype=np.int64)
    cols["reason"] = np.array([s.reason for s in samples], dtype=object).astype(str) \
        if samples else np.array([], dtype=str)
    cols["chunk"] = np.full(len(samples), chunk_id, dtype=np.int64)
    cols["index"] = np.arange(len(samples), dtype=np.int64)
    return cols


# -- plans ---------------------------------------------------------------------------------
def snake_grid(lower: object, upper: object, steps: object) -> np.ndarray:
    """A grid over the box ``[lower, upper]`` (2-D or more) in boustrophedon order, so that
    consecutive points are neighbours (warm starts from the previous point)."""
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    steps = np.broadcast_to(np.asarray(steps, float), lower.shape)
    axes = [np.linspace(lo, hi, int(round((hi - lo) / st)) + 1)
            for lo, hi, st in zip(lower, upper, steps)]
    pts = np.array([[a] for a in axes[-1]])
    for ax in reversed(axes[:-1]):
        rows = []
        for k, a in enumerate(ax):
            block = pts if k % 2 == 0 else pts[::-1]
            rows.append(np.hstack([np.full((len(block), 1), a), block]))
        pts = np.vstack(rows)
    return pts


def band_points(X: Box, lower: object, upper: object, steps: object, lo: float = 0.8,
                hi: float = 1.2) -> np.ndarray:
    """Grid points near the constraints: ``lo·b <= H_i x <= hi·b`` for some row ``i`` of
    ``X = {H x <= b}`` (Section 7.5), in snake order."""
    pts = snake_grid(lower, upper, steps)
    Hx = pts @ np.asarray(X.H).T
    b = np.asarray(X.h)
    near = np.any((Hx >= lo * b) & (Hx <= hi * b), axis=1)
    return pts[near]


def sobol_goals(X: Box, n: int, seed: int = 0, scale: float = 1.5) -> np.ndarray:
    """Goal points: scrambled Sobol points in ``scale ×`` the state-constraint box
    (SPEC §2.30 default)."""
    from scipy.stats import qmc

    centre = 0.5 * (X.lb + X.ub)
    half = 0.5 * scale * (X.ub - X.lb)
    m = max(0, int(math.ceil(math.log2(max(n, 1)))))
    pts = qmc.Sobol(d=X.dim, scramble=True, seed=seed).random_base2(m)[:n]
    return centre - half + 2 * half * pts

#: names that moved out of this module (issue #13): deprecated aliases (errors.moved_names)
__getattr__ = moved_names(__name__, {
    "pendulum_problems": "balustrade.examples.pendulum",
})
