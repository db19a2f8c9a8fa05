"""Per-step time of the rendezvous safety filters (thesis Section 6.5, ``N = 200``):
Algorithm 5.2 (two problems, (5.15) then (5.16)) and Algorithm 6.4 (one problem, (6.15)).

Paths, all timed interleaved on the same states in one run (state by state, path after path):

* balustrade ``default`` (the targets of :mod:`balustrade.reproduce.rendezvous`), ``exact``,
  ``long-horizon``, ``cvxpy`` and ``fast-convex`` (reported "not available" while the preset
  does not exist): wall time of ``controller.step`` (the controller keeps its warm starts);
* ``hand-written Clarabel`` (:mod:`benchmarks._clarabel_direct`): matrices and cones built
  once, only ``b`` updated per step — the baseline: ``x_handwritten = t_path / t_baseline``
  of the medians (the issue's goal for the default: <= 1.0) and ``x_handwritten_paired``, the
  median of the per-state ratios (:func:`paired_ratio`);
* ``cvxpy rebuilt every step`` (the thesis' CVXPY way, rebuilt from scratch);
* PIQP: not applicable — the tube row ``(x−z₀)ᵀP(x−z₀) <= 1`` and the terminal row are convex
  quadratic constraints (second-order cones), so none of (5.15), (5.16), (6.15) is a QP.

The states are those of one disturbed closed loop of the hand-written Algorithm 5.2 (seed 0);
the first state is a warm-up and not in the statistics. The fast paths run the sequence
:data:`REPEATS` times (controllers reset in between, so each pass solves the same problems;
``exact``/``long-horizon`` once): a single pass of 12 states moved medians by ±15 % under load.
(6.15) is solved by the baseline with the bound (6.15g) the ``cvxpy`` path computed at the same
state, so the two solve the same problem. The baseline is verified in the run against the
``cvxpy`` path (same ``h_r``, same fuel objective, same applied input where the optimizer is
unique): a disagreement raises :class:`BaselineMismatch`, so a wrong baseline cannot go
unnoticed. Times are wall times on whatever machine runs it (the thesis: 234 ms and 148 ms,
CVXPY + MOSEK, i7-10510U); ``vs_thesis`` is the thesis time divided by ours. ``quick`` uses ``N
= 30``.
"""

from __future__ import annotations

import time

import cvxpy as cp
import numpy as np

from balustrade.backends.targets import PRESETS
from balustrade.reproduce.rendezvous import controllers, design
from benchmarks._clarabel_direct import DirectRendezvous, RendezvousData

THESIS_S = {"5.2": 0.234, "6.4": 0.148}
#: balustrade paths: label -> preset name (None: the reproduction's default targets)
PATHS = {"default": None, "exact": "exact", "long-horizon": "long-horizon", "cvxpy": "cvxpy",
         "fast-convex": "fast-convex"}
BASELINE = "hand-written Clarabel"
#: passes over the states for the fast paths (``exact``/``long-horizon`` run once)
REPEATS = 3
#: verification tolerances (baseline vs the cvxpy path): h_r and fuel relative (+ absolute),
#: applied input absolute where the fuel-optimal input is unique (fuel > FUEL_UNIQUE)
H_R_RTOL, H_R_ATOL, FUEL_RTOL, FUEL_ATOL, INPUT_ATOL, FUEL_UNIQUE = (
    1e-4, 1e-4, 1e-3, 1e-5, 5e-3, 1e-6)


class BaselineMismatch(AssertionError):
    """The hand-written baseline disagrees with balustrade on the same state."""


def _common(d: dict, z, v) -> list:
    system, s, error = d["system"], d["setup"], d["error"]
    X_E, U_E = error.tighten_state(s.X), error.tighten_input(s.U)
    cons = [z[:, 1:] == system.A @ z[:, :-1] + system.B @ v,
            U_E.H @ v <= U_E.h[:, None]]
    return cons, X_E


def rebuild_alg52(d: dict, x: np.ndarray) -> np.ndarray:
    """(5.15) and (5.16) built from scratch with plain cvxpy; returns the applied input."""
    s, error, cbf = d["setup"], d["error"], d["cbf"]
    n, m, N = 6, 3, s.N
    deltas = s.deltas()
    Pe = error.E.P
    z, v = cp.Variable((n, N + 1)), cp.Variable((m, N))
    cons, X_E = _common(d, z, v)
    xi, xi_N = cp.Variable((X_E.n_rows, N), nonneg=True), cp.Variable(nonneg=True)
    tube = [cp.quad_form(x - z[:, 0], Pe) <= 1]
    state = [X_E.H @ z[:, :N] - X_E.h[:, None] + deltas[None, :] <= xi]
    term = [cp.quad_form(z[:, N], cbf.P) - 1 <= xi_N]
    cp.Problem(cp.Minimize(s.alpha_f * xi_N + cp.sum(xi)), cons + tube + state + term).solve(
        solver="CLARABEL")
    xi_v, xi_N_v = np.maximum(xi.value, 0), max(float(xi_N.value), 0.0)
    z2, v2 = cp.Variable((n, N + 1)), cp.Variable((m, N))
    cons2, _ = _common(d, z2, v2)
    tube2 = [cp.quad_form(x - z2[:, 0], Pe) <= 1]
    state2 = [X_E.H @ z2[:, :N] - X_E.h[:, None] + deltas[None, :] <= xi_v + 1e-6]
    term2 = [cp.quad_form(z2[:, N], cbf.P) - 1 <= xi_N_v + 1e-6]
    cp.Problem(cp.Minimize(cp.sum(cp.abs(v2))), cons2 + tube2 + state2 + term2).solve(
        solver="CLARABEL")
    return v2.value[:, 0] + error.K @ (x - z2.value[:, 0])


def rebuild_alg64(d: dict, x: np.ndarray, bound: float) -> np.ndarray:
    """(6.15) built from scratch with plain cvxpy; returns the applied input."""
    s, error, cbf = d["setup"], d["error"], d["cbf"]
    n, m, N = 6, 3, s.N
    deltas = s.deltas()
    z, v = cp.Variable((n, N + 1)), cp.Variable((m, N))
    cons, X_E = _common(d, z, v)
    xi, xi_N = cp.Variable((X_E.n_rows, N), nonneg=True), cp.Variable(nonneg=True)
    cons += [cp.quad_form(x - z[:, 0], error.E.P) <= 1,
             X_E.H @ z[:, :N] - X_E.h[:, None] + deltas[None, :] <= xi,
             cp.quad_form(z[:, N], cbf.P) - 1 <= xi_N,
             s.alpha_f * xi_N + cp.sum(xi) <= bound]
    cp.Problem(cp.Minimize(cp.sum(cp.abs(v))), cons).solve(solver="CLARABEL")
    return v.value[:, 0] + error.K @ (x - z.value[:, 0])


# -- the paths -----------------------------------------------------------------------------
def preset_available(preset: str | None) -> bool:
    """Whether a path's preset exists in this checkout (``None``: the default targets)."""
    return preset is None or preset in PRESETS


def build_paths(d: dict, names: tuple[str, ...] = tuple(PATHS)) -> tuple[dict, dict]:
    """``({label: {"robust": ctl, "mo": ctl}}, {label: reason not available})``."""
    built, missing = {}, {}
    for label in names:
        preset = PATHS[label]
        if not preset_available(preset):
            missing[label] = f"not available (no preset {preset!r} in this checkout)"
            continue
        ctls = controllers(d, (0.9,), target=preset, record_h_r=False)
        built[label] = {"robust": ctls["robust"], "mo": ctls["mo_rho0.9"]}
    return built, missing


def closed_loop_states(d: dict, direct: DirectRendezvous, steps: int, seed: int = 0
                       ) -> np.ndarray:
    """States of a disturbed closed loop of the hand-written Algorithm 5.2 (``W`` uniform)."""
    system, s = d["system"], d["setup"]
    rng = np.random.default_rng(seed)
    x = np.array(s.x0, dtype=float)
    xs = [x]
    for _ in range(steps - 1):
        ok, u, _, _ = direct.alg52(x)
        if not ok:
            raise BaselineMismatch(f"hand-written Algorithm 5.2 failed at state {x}")
        x = system.step(x, u, rng.uniform(-0.5, 0.5, 3))
        xs.append(x)
    return np.array(xs)


class PathTimes:
    """Per-step wall times and failures of one path for one algorithm (a plain class: the
    ``bench`` command loads this file without registering it as a module, which dataclasses
    need)."""

    def __init__(self) -> None:
        self.times: list[float] = []
        self.iterations: list[int] = []
        self.warmup: list[bool] = []
        self.failed = 0

    def add(self, elapsed: float, ok: bool, iterations: int = 0, warmup: bool = False) -> None:
        self.times.append(elapsed)
        self.iterations.append(iterations)
        self.warmup.append(warmup)
        self.failed += 0 if ok else 1

    def stats(self, skip: int = 1) -> dict:
        """Median and worst over the samples that are not warm-ups (the first state of each
        pass of :func:`measure`; without marked warm-ups the first ``skip`` samples);
        ``skip=0`` keeps every sample."""
        n = len(self.times)
        if any(self.warmup):
            keep = [i for i, w in enumerate(self.warmup) if not (skip and w)]
        else:
            keep = list(range(min(skip, n - 1) if n else 0, n))
        keep = keep or list(range(n))
        t = np.asarray([self.times[i] for i in keep])
        its = [self.iterations[i] for i in keep]
        return {"median_s": float(np.median(t)), "worst_ms": round(1e3 * float(np.max(t)), 2),
                "failed": self.failed, "samples": int(t.size),
                "iterations": float(np.median(its)) if its else 0.0}


class Check:
    """Largest disagreements of the baseline with one balustrade path."""

    def __init__(self) -> None:
        self.h_r = self.fuel = self.u = 0.0
        self.compared = 0

    def note(self, key: str, err: float) -> None:
        setattr(self, key, max(getattr(self, key), float(err)))


def _rel(a: float, b: float, atol: float) -> float:
    """``|a − b| / (atol + rtol |b|)``: <= 1 is agreement."""
    return abs(a - b) / (atol + H_R_RTOL * abs(b)) if np.isfinite(a) else np.inf


def _ok(info) -> bool:
    return info.status == "ok" and not info.fallback


def measure(d: dict, states: np.ndarray, paths: dict, direct: DirectRendezvous,
            reference: str = "cvxpy", repeats: int = 1,
            slow: tuple[str, ...] = ("exact", "long-horizon")) -> tuple[dict, dict]:
    """Time every path on every state, interleaved; ``({(alg, label): PathTimes},
    {(alg, label): Check})`` with the baseline under ``BASELINE``. ``repeats > 1`` runs the
    whole sequence of states again (controllers reset, so every pass sees the same
    problems) for every path except the ``slow`` ones (timed in the first pass only): under
    load one pass of 12 states moves a median by ±15 %; the first state of each pass is
    the warm-up (:meth:`PathTimes.stats` drops it)."""
    times: dict = {}
    checks: dict = {}
    for rep in range(repeats):
        active = {k: v for k, v in paths.items() if rep == 0 or k not in slow}
        _measure_pass(states, active, direct, reference, times, checks)
    return times, checks


def _measure_pass(states: np.ndarray, paths: dict, direct: DirectRendezvous, reference: str,
                  times: dict, checks: dict) -> None:
    """One pass of :func:`measure` over ``states``; appends to ``times`` and ``checks``."""
    for ctls in paths.values():
        ctls["robust"].reset()
        ctls["mo"].reset()
    for j, x in enumerate(states):
        bounds, results = {}, {}
        for label, ctls in paths.items():
            for alg, key in (("5.2", "robust"), ("6.4", "mo")):
                start = time.perf_counter()
                u, info = ctls[key].step(x, np.zeros(3))
                its = sum(s.iterations for s in info.solutions.values())
                times.setdefault((alg, label), PathTimes()).add(time.perf_counter() - start,
                                                                _ok(info), its, j == 0)
                results[(alg, label)] = (u, info)
            bounds[label] = results[("6.4", label)][1].values.get("bound", np.nan)
        bound = bounds.get(reference, next(iter(bounds.values()), np.nan))
        start = time.perf_counter()
        ok52, u52, h_r, fuel52 = direct.alg52(x)
        times.setdefault(("5.2", BASELINE), PathTimes()).add(time.perf_counter() - start, ok52,
                                                             direct.last_iterations, j == 0)
        start = time.perf_counter()
        ok64, u64, fuel64 = direct.alg64(x, bound) if np.isfinite(bound) else (False, None, 0.)
        times.setdefault(("6.4", BASELINE), PathTimes()).add(time.perf_counter() - start, ok64,
                                                             direct.last_iterations, j == 0)
        for (alg, label), (u, info) in results.items():
            c = checks.setdefault((alg, label), Check())
            if not _ok(info):
                continue
            if alg == "5.2" and ok52:
                c.note("h_r", _rel(h_r, info.values["h_r"], H_R_ATOL))
                s2 = info.solutions["filter"]
                c.note("fuel", abs(fuel52 - s2.objective) / (FUEL_ATOL + abs(s2.objective)))
                if s2.objective > FUEL_UNIQUE:
                    c.note("u", np.max(np.abs(u - u52)))
                c.compared += 1
            elif alg == "6.4" and ok64 and label == reference:
                s = info.solutions["problem"]
                c.note("fuel", abs(fuel64 - s.objective) / (FUEL_ATOL + abs(s.objective)))
                if s.objective > FUEL_UNIQUE:
                    c.note("u", np.max(np.abs(u - u64)))
                c.compared += 1


def verify(checks: dict, reference: str = "cvxpy") -> None:
    """Raise :class:`BaselineMismatch` if the baseline disagrees with the reference path."""
    for alg in ("5.2", "6.4"):
        c = checks.get((alg, reference))
        if c is None:
            continue
        bad = (c.h_r > 1.0 or c.fuel > FUEL_RTOL or c.u > INPUT_ATOL or c.compared == 0)
        if bad:
            raise BaselineMismatch(
                f"Alg {alg}: hand-written Clarabel vs balustrade {reference}: h_r err {c.h_r:.2e} "
                f"(scaled, <= 1), fuel rel err {c.fuel:.2e} (<= {FUEL_RTOL}), input err "
                f"{c.u:.2e} (<= {INPUT_ATOL}), {c.compared} states compared")


def paired_ratio(path: PathTimes, base: PathTimes) -> float:
    """Median over the timed samples of ``t_path / t_baseline`` on the same state of the same
    pass (samples are appended state by state in both, a ``slow`` path's being the first
    pass): the state-to-state spread (60–500 ms per step at ``N = 200``) cancels in each
    ratio, which a ratio of medians keeps."""
    if len(path.times) > len(base.times):
        raise BaselineMismatch(f"paired_ratio: the path has {len(path.times)} samples, the "
                               f"baseline only {len(base.times)}")
    keep = [i for i in range(len(path.times)) if not path.warmup[i]]
    if any(path.warmup[i] != base.warmup[i] for i in range(len(path.times))):
        raise BaselineMismatch("paired_ratio: the samples of the path and the baseline are "
                               "not aligned state by state")
    return float(np.median([path.times[i] / base.times[i] for i in keep])) if keep else np.nan


def rows_for(N: int, times: dict, checks: dict, missing: dict) -> list[dict]:
    """Benchmark rows: per algorithm, the baseline then every path (ratio to the baseline)."""
    rows = []
    for alg in ("5.2", "6.4"):
        base = times[(alg, BASELINE)].stats()
        rows.append({"name": f"rendezvous Alg {alg} N={N}: {BASELINE} (baseline)", **base,
                     "thesis_ms": THESIS_S[alg] * 1e3,
                     "vs_thesis": round(THESIS_S[alg] / base["median_s"], 2)})
        for (a, label), pt in times.items():
            if a != alg or label == BASELINE:
                continue
            st = pt.stats()
            row = {"name": f"rendezvous Alg {alg} N={N}: balustrade {label}", **st,
                   "x_handwritten": round(st["median_s"] / base["median_s"], 2),
                   "x_handwritten_paired": round(paired_ratio(pt, times[(alg, BASELINE)]), 3),
                   "vs_thesis": round(THESIS_S[alg] / st["median_s"], 2)}
            c = checks.get((alg, label))
            if c is not None and c.compared:
                row["agree"] = f"h_r {c.h_r:.1e} fuel {c.fuel:.1e} u {c.u:.1e}"
            if alg == "6.4":
                row["mo_over_robust"] = round(st["median_s"] / times[("5.2", label)].stats()[
                    "median_s"], 2)
            rows.append(row)
        for label, reason in missing.items():
            rows.append({"name": f"rendezvous Alg {alg} N={N}: balustrade {label}",
                         "status": reason})
        rows.append({"name": f"rendezvous Alg {alg} N={N}: PIQP",
                     "status": "not applicable: tube/terminal rows are second-order cones"})
    return rows


def run(quick: bool = False) -> list[dict]:
    N, T = (30, 40) if quick else (200, 40)
    n_timed = 8 if quick else 12
    d = design(N, T)
    direct = DirectRendezvous(RendezvousData.from_design(d))
    states = closed_loop_states(d, direct, n_timed + 1)
    paths, missing = build_paths(d)
    times, checks = measure(d, states, paths, direct, repeats=1 if quick else REPEATS)
    verify(checks)
    rows = rows_for(N, times, checks, missing)
    # the thesis' way: cvxpy rebuilt every step, on the same states
    base52, base64 = PathTimes(), PathTimes()
    mo = paths["cvxpy"]["mo"]
    mo.reset()
    for x in states[: max(3, n_timed // 2)]:
        start = time.perf_counter()
        rebuild_alg52(d, x)
        base52.add(time.perf_counter() - start, True)
        _, info = mo.step(x, np.zeros(3))  # the loop's bound (6.15g) at this state
        start = time.perf_counter()
        rebuild_alg64(d, x, info.values["bound"] + 1e-6)
        base64.add(time.perf_counter() - start, True)
    for alg, pt in (("5.2", base52), ("6.4", base64)):
        st = pt.stats(skip=0)
        base = times[(alg, BASELINE)].stats()
        rows.append({"name": f"rendezvous Alg {alg} N={N}: cvxpy rebuilt every step", **st,
                     "x_handwritten": round(st["median_s"] / base["median_s"], 2),
                     "vs_thesis": round(THESIS_S[alg] / st["median_s"], 2)})
    return rows
