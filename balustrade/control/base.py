"""One controller interface and the closed-loop runner.

A controller maps a measured state and a proposed input to the applied input:
``step(x, u_p) -> (u, StepInfo)``. It must never raise for a failed solve: it applies the
fallback its algorithm prescribes and records it in :class:`StepInfo` (DESIGN.md
principle 4). :func:`simulate` records states, inputs, proposals, value functions,
statuses, fallbacks and solve times.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol

import numpy as np

from balustrade._checks import as_count, as_float_array, as_vector
from balustrade.control.plant import Plant, check_plant
from balustrade.dsl.system import System
from balustrade.errors import BalustradeError, NonFiniteError, ShapeError

if TYPE_CHECKING:
    from balustrade.backends.solution import Solution


@dataclass
class StepInfo:
    """What a controller did at one step.

    ``uncertified`` maps each solve the step relied on that did not end ``optimal`` to its
    status (e.g. ``{"slack": "optimal_inaccurate"}``): values computed from it are not
    certified optima (see :func:`note_solve`); a solve stopped by its target's budget is
    recorded with the word :data:`TRUNCATED` (real-time mode), also in ``status``."""

    status: str = "ok"
    fallback: str | None = None
    values: dict[str, float] = field(default_factory=dict)
    solve_time: float = 0.0
    solutions: dict = field(default_factory=dict, repr=False)
    uncertified: dict[str, str] = field(default_factory=dict)


#: the status word of a solve stopped by its target's budget (real-time mode, issue #14 §5,
#: :meth:`balustrade.backends.Target.with_budget`): used in ``StepInfo.status`` and as the
#: reason in ``StepInfo.uncertified`` in place of the status of the iteration limit
TRUNCATED = "truncated"


#: the status words of a step that did what its algorithm prescribes on solves that ended
#: ``optimal`` (or on none):
#:
#: * ``"ok"`` — every solve of the step ended ``optimal`` (or, Algorithm 8.7, a grid
#:   candidate met the decrease ``ĥ(f(x, u_i)) <= ρ ĥ(x)``);
#: * ``"certified"`` — nothing was solved: the PCBF filter's (2.24) skipped on the
#:   shifted-plan certificate (``certificate_first``, a certified ``h_PB = 0``), or
#:   Algorithm 7.5's certification shortcut (line 4, ``ĥ(f(x, u_p)) <= 0``);
#: * ``"proposal_feasible"`` — Algorithm 7.5 after an optimal (7.6): ``u_p ∈ U`` meets the
#:   decrease of (7.5), whose cost is 0 there, so ``u_p`` is its exact minimiser (no
#:   fallback, no (7.5) solve).
#:
#: Any other word names a solve that did not end optimal (``"filter_<status>"``,
#: ``"max_decrease_failed"``, ``"error: …"``, :data:`TRUNCATED`), a fallback
#: (``"no_decreasing_candidate"``) or bad data (``"non_finite_state"``,
#: ``"non_finite_proposal[_<status>]"``).
SUCCEEDED = frozenset({"ok", "certified", "proposal_feasible"})


def step_succeeded(status: str) -> bool:
    """Whether a step with this ``StepInfo.status`` succeeded (:data:`SUCCEEDED`): what
    failure counters of closed loops count as a success; counters of solved (2.24)
    problems separate ``"certified"`` (nothing was solved) from ``"ok"``."""
    return status in SUCCEEDED


def outcome(sol: Solution) -> str:
    """How a solve ended, as a controller records it: :data:`TRUNCATED` for a solve stopped
    by its budget, else its status."""
    return TRUNCATED if getattr(sol, "truncated", False) else str(sol.status)


def feasible_truncation(sol: Solution) -> bool:
    """A solve stopped by its budget whose iterate meets every constraint row and bound
    within :data:`~balustrade.backends.solution.FEASIBILITY_TOL`
    (:meth:`~balustrade.backends.Solution.feasible_within`): not optimal, but a feasible
    point of the problem."""
    return bool(getattr(sol, "truncated", False)) and sol.feasible_within()


def note_solve(info: StepInfo, name: str, status: str) -> bool:
    """Record in ``info.uncertified`` a solve of problem ``name`` whose status is not
    ``optimal``; returns whether it was ``optimal``."""
    if status != "optimal":
        info.uncertified[name] = status
    return status == "optimal"


class Controller(Protocol):
    """The closed-loop interface every algorithm of :mod:`balustrade.control` implements."""

    def step(self, x: np.ndarray, u_p: np.ndarray) -> tuple[np.ndarray, StepInfo]: ...

    def reset(self) -> None: ...


@dataclass
class Trace:
    """A recorded closed-loop run."""

    states: np.ndarray
    inputs: np.ndarray
    proposed: np.ndarray
    disturbances: np.ndarray
    values: dict[str, np.ndarray]
    statuses: list[str]
    fallbacks: list[str | None]
    solve_times: np.ndarray
    step_times: np.ndarray
    infos: list[StepInfo] = field(repr=False, default_factory=list)
    stopped: str | None = None
    #: per step, :attr:`StepInfo.uncertified` (solves used that did not end ``optimal``)
    uncertified: list[dict[str, str]] = field(default_factory=list)

    @property
    def n_fallbacks(self) -> int:
        return sum(f is not None for f in self.fallbacks)

    @property
    def n_uncertified(self) -> int:
        """Steps that relied on at least one solve not certified ``optimal``."""
        return sum(bool(u) for u in self.uncertified)

    @property
    def truncated_steps(self) -> list[int]:
        """The steps with at least one solve stopped by its budget (real-time mode): the
        status word :data:`TRUNCATED` in the step's status or its uncertified solves."""
        unc = self.uncertified + [{}] * (len(self.statuses) - len(self.uncertified))
        return [k for k, (s, u) in enumerate(zip(self.statuses, unc))
                if TRUNCATED in s or TRUNCATED in u.values()]

    @property
    def n_truncated(self) -> int:
        """How many steps had a solve stopped by its budget (:attr:`truncated_steps`)."""
        return len(self.truncated_steps)

    def plot(self, path: str | None = None, **options: object) -> object:
        """A matplotlib figure of the run, saved to ``path`` if given (see
        :func:`balustrade.control.trace.plot_trace` for the options)."""
        from balustrade.control.trace import plot_trace

        return plot_trace(self, path, **options)

    def save(self, path: str) -> tuple:
        """Write ``<path>.csv`` (a tidy per-step table) and ``<path>.json`` (metadata)."""
        from balustrade.control.trace import save_trace

        return save_trace(self, path)

    @classmethod
    def load(cls, path: str) -> Trace:
        """Read a run written by :meth:`save`."""
        from balustrade.control.trace import load_trace

        return load_trace(path)


Proposal = np.ndarray | float | Callable[[int, np.ndarray], np.ndarray]
Disturbance = np.ndarray | Callable[[int, np.ndarray], np.ndarray] | None


def simulate(plant: System | Plant, controller: Controller, x0: np.ndarray, steps: int,
             proposal: Proposal = 0.0, disturbance: Disturbance = None,
             keep_infos: bool = False) -> Trace:
    """Run ``steps`` closed-loop steps ``x_{k+1} = f(x_k, u_k, w_k)`` from ``x0``.

    ``plant`` is a discrete :class:`System` or a continuous-time
    :class:`~balustrade.control.plant.ContinuousPlant` (integrated over each sample with the
    input held). ``proposal`` is a constant ``u_p`` or ``u_p(k, x)``; ``disturbance`` is an
    array ``(steps, nw)`` or ``w(k, x)``. If the state stops being finite (divergence), the
    run stops and ``Trace.stopped`` says why; it never raises for solver failures.
    """
    plant = check_plant(plant, "simulate")
    if not callable(getattr(controller, "step", None)):
        raise BalustradeError(f"simulate: controller must have a step(x, u_p) method, got "
                              f"{type(controller).__name__}")
    x = as_vector(x0, "simulate: x0", plant.nx)
    steps = as_count(steps, "simulate: steps")
    disturbance = _disturbance_table(disturbance, steps, plant.nw)
    states, inputs, proposed, dists = [x], [], [], []
    values: dict[str, list[float]] = {}
    statuses, fallbacks, solve_times, step_times, infos = [], [], [], [], []
    uncertified: list[dict[str, str]] = []
    stopped = None
    for k in range(steps):
        u_p = _proposal(proposal, k, x, plant.nu)
        start = time.perf_counter()
        out = controller.step(x, u_p)
        step_times.append(time.perf_counter() - start)
        if not (isinstance(out, tuple) and len(out) == 2 and isinstance(out[1], StepInfo)):
            raise BalustradeError(f"simulate: {type(controller).__name__}.step must return "
                                  f"(u, StepInfo), got {type(out).__name__} at step {k}")
        u, info = out
        u = as_vector(u, "simulate: controller output u", plant.nu, finite=False)
        w = _disturbance(disturbance, k, x, plant.nw)
        inputs.append(u)
        proposed.append(u_p)
        dists.append(w)
        statuses.append(info.status)
        fallbacks.append(info.fallback)
        uncertified.append(dict(info.uncertified))
        solve_times.append(info.solve_time)
        for key in set(values) | set(info.values):
            values.setdefault(key, [np.nan] * k).append(info.values.get(key, np.nan))
        if keep_infos:
            infos.append(info)
        if not np.all(np.isfinite(u)):
            stopped = f"non-finite input at step {k}"
            break
        x = plant.step(x, u, w if plant.nw else None)
        if not np.all(np.isfinite(x)) or np.max(np.abs(x)) > 1e12:
            stopped = f"state diverged at step {k + 1}"
            states.append(x)
            break
        states.append(x)
    return Trace(np.array(states), np.array(inputs).reshape(-1, plant.nu),
                 np.array(proposed).reshape(-1, plant.nu),
                 np.array(dists).reshape(len(dists), plant.nw),
                 {k: np.array(v) for k, v in values.items()}, statuses, fallbacks,
                 np.array(solve_times), np.array(step_times), infos, stopped, uncertified)


def _call(fn: Callable, k: int, x: np.ndarray, what: str) -> object:
    """The user's ``fn(k, x)``; its failure is reported with the step."""
    try:
        return fn(k, x)
    except BalustradeError:
        raise
    except Exception as exc:  # the user's function failed
        raise BalustradeError(f"simulate: {what}(k, x) failed at step {k}: "
                              f"{type(exc).__name__}: {exc}") from exc


def _proposal(proposal: Proposal, k: int, x: np.ndarray, nu: int) -> np.ndarray:
    value = _call(proposal, k, x, "proposal") if callable(proposal) else proposal
    block = "simulate: proposed input u_p"
    arr = as_float_array(value, block)
    return as_vector(np.broadcast_to(arr, (nu,)) if arr.ndim == 0 else arr, block, nu)


def _disturbance_table(disturbance: Disturbance, steps: int, nw: int) -> Disturbance:
    """Check a disturbance sequence up front: ``(steps, nw)`` (or longer), finite."""
    if disturbance is None or callable(disturbance):
        return disturbance
    table = as_float_array(disturbance, "simulate: disturbance sequence")
    if nw == 0:
        return None
    if table.ndim == 1 and nw == 1:
        table = table.reshape(-1, 1)
    if table.ndim != 2 or table.shape[1] != nw or table.shape[0] < steps:
        raise ShapeError("simulate: disturbance sequence", f"({steps}, {nw}) (one row per step)",
                         table.shape, what="shape")
    bad = np.flatnonzero(~np.all(np.isfinite(table[:steps]), axis=1))
    if bad.size:
        raise NonFiniteError(f"simulate: disturbance sequence contains NaN or inf at steps "
                             f"{bad.tolist()}")
    return table


def _disturbance(disturbance: Disturbance, k: int, x: np.ndarray, nw: int) -> np.ndarray:
    if disturbance is None or nw == 0:
        return np.zeros(nw)
    value = _call(disturbance, k, x, "disturbance") if callable(disturbance) \
        else np.asarray(disturbance)[k]
    return as_vector(value, f"simulate: disturbance at step {k}", nw)
