"""The exact PCBF algorithm of §8.3 ((2.24) then (2.23), N = 50, nine discs, ``v_N = 0``)
in Python and as emitted C (issue #16: "PCBF <= 50 ms").

``python -m benchmarks.obstacles_pcbf_c [--target structured-ip] [--states 200]
[--steps 70] [--build-dir DIR] [--no-certificate-first] [--shifted-retry-solver K]
[--fatrop-stall TOL,ITERS|off] [--out FILE]``

* The filter is :func:`balustrade.reproduce.obstacles.pcbf_algorithm` with ``target``,
  ``shifted=False`` and ``shifted_retry_solver`` (default
  :data:`~balustrade.reproduce.obstacles.SHIFTED_RETRY_SOLVER`, -1: the chain's last solver
  makes the shifted-plan attempt; 0 is session 12's, the first solver); the emitted C
  warm-starts (2.24) from its last solution, so the Python filter does too (same
  decisions) and ``stall_stop`` (default :data:`~balustrade.reproduce.obstacles.
  STALL`, fatrop's stall stop, a failure that moves the chain on; ``off``: none;
  session 14); its C through
  :func:`~balustrade.codegen.accelerate` (:func:`~balustrade.codegen.emit_pcbf`, one call
  per step; with ``structured-ip`` it links the casadi wheel's libfatrop/libblasfeo and
  libipopt, the chain's last resort). Build time and source size are reported (the build
  is cached in ``--build-dir``).
* The 5 reference closed loops (the naive MPC (8.2) as proposal, 70 steps), the Python and
  the C filter run as two closed loops interleaved step by step (each with its own naive
  MPC): median / 90th percentile / worst step time, statuses, the minimum signed distance
  per start, and C = Python: the largest input and state difference and the steps whose
  status or fallback differ.
* ``--states`` cold steps (both filters reset) at random states of the sampling domain
  outside the discs with random proposals in ``U``: statuses and inputs compared.

Times are wall times seen from Python (the C's include the ctypes call); the machine is
shared, so they are under load. The loops also report the process CPU time per step
(``python_cpu``, ``c_cpu``; less bound to the load than the wall time, not free of it).
"""

from __future__ import annotations

import argparse
import json
import time
from collections import Counter
from pathlib import Path

import numpy as np

from balustrade.control.plant import check_plant
from balustrade.models.obstacle_car import obstacle_car, obstacle_setup, signed_distance
from balustrade.reproduce import obstacles as O

BUILD_DIR = Path("/tmp/balustrade-obstacles-pcbf-c")


def build_pair(target: str = "structured-ip", build_dir: str | Path = BUILD_DIR,
               certificate_first: bool = True,
               shifted_retry_solver: int = O.SHIFTED_RETRY_SOLVER,
               stall_stop: tuple[float, int] | None = O.STALL) -> dict:
    """The Python PCBF algorithm on ``target`` and its emitted C (cached build)."""
    py = O.pcbf_algorithm(target, shifted=False, certificate_first=certificate_first,
                          shifted_retry_solver=shifted_retry_solver, stall_stop=stall_stop)
    # the Python backend builds its retry solvers on first use (~0.2 s under load), the C
    # allocates them at init: built here, so that no step's time includes a build
    for prob in (py.slack, py.filter):
        getattr(prob, "_retry_solvers", lambda: None)()
    t = time.perf_counter()
    c = O.pcbf_algorithm_c(target, build_dir=build_dir, certificate_first=certificate_first,
                           shifted_retry_solver=shifted_retry_solver, stall_stop=stall_stop)
    wall = time.perf_counter() - t
    acc = c.accelerated
    d = Path(acc["dir"])
    size = sum(p.stat().st_size for p in d.rglob("*.[ch]"))
    return {"py": py, "c": c, "shifted_retry_solver": shifted_retry_solver,
            "stall_stop": stall_stop,
            "build_s": acc["build_s"], "cached": acc["cached"],
            "accelerate_s": wall, "source_bytes": size, "dir": str(d),
            "link_flags": list(c._lib.manifest.get("link_flags", []))}


def _stats(times_ms: list[float]) -> dict:
    t = np.asarray(times_ms, float)
    return {"median_ms": float(np.median(t)), "p90_ms": float(np.percentile(t, 90)),
            "worst_ms": float(t.max()), "n": int(t.size)}


def lockstep_loops(py: object, c: object, starts: tuple = O.STARTS, steps: int = O.STEPS
                   ) -> dict:
    """The Python and the C filter as two closed loops of the car (each with its own naive
    MPC), interleaved step by step; per start and overall: times, statuses, min distance,
    C = Python."""
    plant, s = check_plant(obstacle_car(), "obstacles_pcbf_c"), obstacle_setup()
    mpcs = {"py": O.NaiveMPC(), "c": O.NaiveMPC()}
    filters = {"py": py, "c": c}
    times: dict[str, list[float]] = {"py": [], "c": []}
    cpu: dict[str, list[float]] = {"py": [], "c": []}  # process CPU time, less load-bound
    where: list[tuple] = []  # (start, step, Python status) of every step, for the worst
    statuses: dict[str, list[str]] = {"py": [], "c": []}
    per_start = []
    max_du = max_dx = 0.0
    differ: list[tuple] = []  # (start, step, Python status, C status) where they differ
    for p in starts:
        x0 = O.initial_state(p)
        xs = {k: [x0.copy()] for k in filters}
        st: dict[str, list[str]] = {"py": [], "c": []}
        for k in filters:
            mpcs[k].start(x0)
            filters[k].reset()
        for step in range(steps):
            out = {}
            for k in ("py", "c"):
                x = xs[k][-1]
                u_p = mpcs[k](step, x)
                t, tc = time.perf_counter(), time.process_time()
                u, info = filters[k].step(x, u_p)
                times[k].append(1e3 * (time.perf_counter() - t))
                cpu[k].append(1e3 * (time.process_time() - tc))
                st[k].append(info.status)
                out[k] = (u, info)
                xs[k].append(plant.step(x, u, None))
            (u_py, i_py), (u_c, i_c) = out["py"], out["c"]
            s2 = i_py.solutions.get("filter")
            where.append((list(p), step, i_py.status, i_c.status,
                          None if s2 is None else f"{s2.solver}, {s2.iterations} iterations: "
                          f"{s2.message[:160]}"))
            max_du = max(max_du, float(np.max(np.abs(u_py - u_c))))
            if (i_py.status, i_py.fallback) != (i_c.status, i_c.fallback):
                differ.append((list(p), step, i_py.status, i_c.status))
        row = {"start": list(p)}
        for k in filters:
            X = np.array(xs[k])
            row[f"min_distance_{k}"] = float(signed_distance(X, s.obstacles).min())
            row[f"statuses_{k}"] = dict(Counter(st[k]))
            statuses[k] += st[k]
        max_dx = max(max_dx, float(np.max(np.abs(np.array(xs["py"]) - np.array(xs["c"])))))
        per_start.append(row)
    worst = {k: where[int(np.argmax(times[k]))] for k in filters}
    # the 5 slowest steps of each, with the Python (2.23) chain's summary (same in C)
    slowest = {k: [[round(times[k][i], 1), *where[i]] for i in np.argsort(times[k])[-5:][::-1]]
               for k in filters}
    return {"per_start": per_start, "python": _stats(times["py"]), "c": _stats(times["c"]),
            "python_cpu": _stats(cpu["py"]), "c_cpu": _stats(cpu["c"]),
            "slowest_steps_cpu": {k: [[round(cpu[k][i], 1), *where[i][:3]]
                                      for i in np.argsort(cpu[k])[-5:][::-1]] for k in filters},
            "worst_step": worst, "slowest_steps": slowest,
            "without_first_step": {k: _stats([t for t, w in zip(times[k], where) if w[1]])
                                   for k in filters},
            "statuses_py": dict(Counter(statuses["py"])),
            "statuses_c": dict(Counter(statuses["c"])),
            "max_du": max_du, "max_dx": max_dx, "steps_status_differs": len(differ),
            "status_differs": differ,
            "min_distance_py": min(r["min_distance_py"] for r in per_start),
            "min_distance_c": min(r["min_distance_c"] for r in per_start)}


def random_states(n: int, seed: int = 0, clearance: float = 0.02) -> tuple[np.ndarray,
                                                                         np.ndarray]:
    """``n`` states of the sampling domain at least ``clearance`` outside every disc and
    proposals uniform in ``U``."""
    s = obstacle_setup()
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(s.domain.lb, float), np.asarray(s.domain.ub, float)
    out: list[np.ndarray] = []
    while len(out) < n:
        x = rng.uniform(lo, hi)
        if signed_distance(x[None], s.obstacles).min() >= clearance:
            out.append(x)
    u = rng.uniform(np.asarray(s.U.lb, float), np.asarray(s.U.ub, float), size=(n, 2))
    return np.array(out), u


def compare_states(py: object, c: object, states: np.ndarray, u_p: np.ndarray) -> dict:
    """Cold steps (both filters reset) at ``states``: statuses and inputs, C vs Python."""
    max_du, differ, st_py, t_py, t_c = 0.0, [], [], [], []
    for i, (x, up) in enumerate(zip(states, u_p)):
        py.reset()
        c.reset()
        t = time.perf_counter()
        u1, i1 = py.step(x, up)
        t_py.append(1e3 * (time.perf_counter() - t))
        t = time.perf_counter()
        u2, i2 = c.step(x, up)
        t_c.append(1e3 * (time.perf_counter() - t))
        st_py.append(i1.status)
        if (i1.status, i1.fallback) != (i2.status, i2.fallback):
            differ.append((i, i1.status, i2.status))
        max_du = max(max_du, float(np.max(np.abs(u1 - u2))))
    return {"n": len(states), "statuses_py": dict(Counter(st_py)),
            "status_differs": differ, "max_du": max_du,
            "python_cold": _stats(t_py), "c_cold": _stats(t_c)}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--target", default="structured-ip")
    ap.add_argument("--states", type=int, default=200)
    ap.add_argument("--steps", type=int, default=O.STEPS)
    ap.add_argument("--build-dir", default=str(BUILD_DIR))
    ap.add_argument("--out", default=None, help="write the metrics as JSON here")
    ap.add_argument("--no-certificate-first", action="store_true",
                    help="solve (2.24) at every step (certificate_first=False)")
    ap.add_argument("--shifted-retry-solver", type=int, default=O.SHIFTED_RETRY_SOLVER,
                    help="the (2.23) chain's solver of a certified step's attempt from the "
                         "shifted plan (0 the first, -1 the last)")
    ap.add_argument("--fatrop-stall", default=None, metavar="TOL,ITERS",
                    help="fatrop's stall stop (tol_acceptable, acceptable_iter; a failure "
                         "that moves the chain on); 'off': none; default "
                         f"{O.STALL}")
    a = ap.parse_args(argv)
    stall = O.STALL
    if a.fatrop_stall == "off":
        stall = None
    elif a.fatrop_stall:
        tol, iters = a.fatrop_stall.split(",")
        stall = (float(tol), int(iters))
    pair = build_pair(a.target, a.build_dir, not a.no_certificate_first,
                      a.shifted_retry_solver, stall)
    res: dict = {"target": a.target, **{k: v for k, v in pair.items() if k not in ("py", "c")}}
    print(json.dumps(res), flush=True)
    res["loops"] = lockstep_loops(pair["py"], pair["c"], steps=a.steps)
    print(json.dumps(res["loops"]), flush=True)
    if a.states:
        res["states"] = compare_states(pair["py"], pair["c"], *random_states(a.states))
        print(json.dumps(res["states"]), flush=True)
    if a.out:
        Path(a.out).write_text(json.dumps(res, indent=1))
    return res


if __name__ == "__main__":
    main()
