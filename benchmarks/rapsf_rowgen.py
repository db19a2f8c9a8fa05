"""Row generation against the full solve of (4.5) on the closed-loop states of the RAPSF bench
(docs/adaptive.md, "session 12: row generation")::

    PYTHONPATH=$PWD python -m benchmarks.rapsf_rowgen [masses] [steps]
    PYTHONPATH=$PWD python -m benchmarks.rapsf_rowgen loop [masses] [steps] [drop_after]
    PYTHONPATH=$PWD python -m benchmarks.rapsf_rowgen versions [masses] [steps] [path]

The closed loop of :class:`benchmarks.bench_rapsf.Loop` (design of ``reproduce msd-adaptive``,
box update, ``fast-convex``) runs ``steps`` steps and records the parameters of every solve of
the main horizon. Then, state by state in the loop's order, the same compiled problem is solved
whole (PIQP set up once, the default) and by row generation
(:mod:`balustrade.backends.row_generation`) in a few configurations (rows added per violated
group and round; the seed from the previous state), all taking turns state by state.
Reported: time per solve (median/worst), rounds, final rows, the largest
``|v_0|`` and objective differences, the statuses. ``loop``: whole closed loops of
Algorithm 4.1 with and without row generation, taking turns every step (:func:`loops`).
``versions``: closed loops with row generation by this checkout's
:class:`~balustrade.backends.row_generation.RowGeneration` and by the one in another copy of
``row_generation.py`` (``path``, e.g. ``/work/main/balustrade/backends/row_generation.py``;
default: this checkout's with ``reuse_solver=False``), taking turns every step
(:func:`versions`).
"""

from __future__ import annotations

import copy
import importlib.util
import sys
import time

import numpy as np

from balustrade.backends import resolve_target
from balustrade.backends.solution import Status
from balustrade.reproduce import msd_adaptive
from benchmarks.bench_rapsf import Loop


def record(masses: int, steps: int) -> tuple[object, list[dict]]:
    """The compiled main-horizon problem of the closed loop and the parameters of its solves."""
    d = msd_adaptive.design(masses)
    ctrl = msd_adaptive.adaptive_controller(d, target="fast-convex")
    loop = Loop(d, ctrl.step, steps)
    loop(0)
    seen: list[tuple[object, dict]] = []
    for compiled in ctrl._compiled.values():
        solve = compiled.solve

        def wrapped(params=None, warm_start=None, _solve=solve, _c=compiled):
            seen.append((_c, copy.deepcopy(params)))
            return _solve(params, warm_start=warm_start)
        compiled.solve = wrapped
    for k in range(1, steps):
        loop(k)
    main = max({id(c): c for c, _ in seen}.values(), key=lambda c: c.ocp.N)
    return main, [p for c, p in seen if c is main]


def compare(compiled: object, states: list[dict], configs: list[dict]) -> dict:
    """The full solve and row generation with each of ``configs`` (keywords of
    :class:`~balustrade.backends.row_generation.RowGeneration`), taking turns state by state."""
    full = copy.copy(compiled)
    full.rowgen = None
    runs = {"full": full}
    for cfg in configs:
        gen = copy.copy(compiled)
        gen.rowgen = compiled._row_generation(cfg)
        runs[" ".join(f"{k}={v}" for k, v in cfg.items())
             if "reduced_options" not in cfg else "preset fast-convex-rowgen"] = gen
    for c in runs.values():
        c.__dict__.pop("solve", None)  # the recording wrapper of record()
    out = {label: {"t": [], "rounds": [], "rows": [], "dv": [], "dobj": [], "status": set()}
           for label in runs}
    for params in states:
        ref = None
        for label, c in runs.items():
            t0 = time.perf_counter()
            sol = c.solve(params)
            r = out[label]
            r["t"].append(time.perf_counter() - t0)
            r["status"].add(sol.status.value)
            if c.rowgen is not None:
                r["rounds"].append(c.rowgen.stats.rounds)
                r["rows"].append(c.rowgen.stats.rows)
            if ref is None:
                ref = sol
            elif ref.status == Status.OPTIMAL and sol.status == Status.OPTIMAL:
                r["dv"].append(float(np.max(np.abs(ref.primal["v"][:, 0]
                                                   - sol.primal["v"][:, 0]))))
                r["dobj"].append(abs(ref.objective - sol.objective))
    return out


def loops(masses: int, steps: int, drop_after: int | None = None) -> dict:
    """Closed loops of Algorithm 4.1 with the same ``θ*`` and disturbances, taking turns every
    step: the controller without row generation (the old default), with it (the default
    choice of :class:`~balustrade.control.rapsf.RAPSF`), and (``drop_after`` given) with it
    dropping rows idle for ``drop_after`` solves from the seed. Per loop: step times, the
    inputs' largest difference from the old default's, fallbacks."""
    d = msd_adaptive.design(masses)
    ctrls = {"full (old default)": msd_adaptive.adaptive_controller(d, target="fast-convex"),
             "row generation": msd_adaptive.adaptive_controller(d, target="fast-convex")}
    if drop_after is not None:
        ctrls[f"row generation, drop_after={drop_after}"] = \
            msd_adaptive.adaptive_controller(d, target="fast-convex")
    ctrls["full (old default)"].row_generation = False
    runs = {label: Loop(d, c.step, steps) for label, c in ctrls.items()}
    for k in range(steps):
        for label, loop in runs.items():
            loop(k)
            if k == 0 and "drop_after" in label:
                for c in ctrls[label]._compiled.values():
                    if c.rowgen is not None:
                        c.rowgen.drop_after = drop_after
    ref = np.array(runs["full (old default)"].applied)
    return {label: {"median": float(np.median(loop.times[1:])),
                    "worst": float(np.max(loop.times[1:])), "fallbacks": loop.fallbacks,
                    "max_du": float(np.max(np.abs(np.array(loop.applied) - ref))),
                    "rowgen": any(getattr(c, "rowgen", None) is not None
                                  for c in ctrls[label]._compiled.values()),
                    "rows": [c.rowgen.stats.rows for c in ctrls[label]._compiled.values()
                             if getattr(c, "rowgen", None) is not None]}
            for label, loop in runs.items()}


def _row_generation_class(path: str | None) -> type:
    """``RowGeneration`` of the module file ``path`` (``None``: this checkout's)."""
    if path is None:
        from balustrade.backends.row_generation import RowGeneration
        return RowGeneration
    spec = importlib.util.spec_from_file_location("_other_row_generation", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module             # dataclasses look their module up
    spec.loader.exec_module(module)
    return module.RowGeneration


def versions(masses: int, steps: int, path: str | None = None) -> dict:
    """Two closed loops of Algorithm 4.1 with row generation (the preset chosen by
    :class:`~balustrade.control.rapsf.RAPSF`), the same ``θ*`` and disturbances, taking turns
    every step (which goes first alternates): this checkout's ``RowGeneration`` and the one of
    ``path`` (``None``: this checkout's with ``reuse_solver=False``, i.e. a new PIQP solver
    per round as in session 12). The other loop's row generation is swapped in after the
    first step (which compiles; its working set carried over). Per loop: step times, rounds
    per step; the largest input difference between the two; per-step time ratios."""
    other_cls = _row_generation_class(path)
    d = msd_adaptive.design(masses)
    ctrls = {"this checkout": msd_adaptive.adaptive_controller(d, target="fast-convex"),
             "other": msd_adaptive.adaptive_controller(d, target="fast-convex")}
    runs = {label: Loop(d, c.step, steps) for label, c in ctrls.items()}
    rounds: dict[str, list[int]] = {label: [] for label in runs}
    for loop in runs.values():
        loop(0)
    setting = dict(resolve_target("fast-convex-rowgen").options["row_generation"])
    if path is None:
        setting["reuse_solver"] = False
    for c in ctrls["other"]._compiled.values():
        if c.rowgen is not None:
            seed = c.rowgen._seed
            c.rowgen = other_cls(c.program, c.rowgen.groups, stride=c.rowgen.stride,
                                 options=c.options, **setting)
            c.rowgen._seed = seed
    for k in range(1, steps):
        for label in (list(runs) if k % 2 else list(runs)[::-1]):
            runs[label](k)
            gens = [c.rowgen for c in ctrls[label]._compiled.values()
                    if getattr(c, "rowgen", None) is not None]
            rounds[label].append(gens[0].stats.rounds if gens else 0)
    t = {label: np.array(loop.times[1:]) for label, loop in runs.items()}
    du = float(np.max(np.abs(np.array(runs["this checkout"].applied)
                             - np.array(runs["other"].applied))))
    return {"median": {k: float(np.median(v)) for k, v in t.items()},
            "mean": {k: float(np.mean(v)) for k, v in t.items()},
            "ratio_median": float(np.median(t["other"] / t["this checkout"])),
            "rounds": rounds, "max_du": du,
            "fallbacks": {k: loop.fallbacks for k, loop in runs.items()}}


def main(argv: list[str]) -> None:
    if argv and argv[0] == "versions":
        masses = int(argv[1]) if len(argv) > 1 else 8
        steps = int(argv[2]) if len(argv) > 2 else 30
        path = argv[3] if len(argv) > 3 else None
        r = versions(masses, steps, path)
        print(f"{masses} masses, closed loops of {steps} steps taking turns (first step not "
              f"timed; under load); other = {path or 'this checkout, reuse_solver=False'}")
        for label in r["median"]:
            print(f"  {label:<14} median step {1e3 * r['median'][label]:8.2f} ms  mean "
                  f"{1e3 * r['mean'][label]:8.2f} ms  rounds per step "
                  f"{np.bincount(r['rounds'][label]).tolist()} (count of 0, 1, 2, … rounds)  "
                  f"fallbacks {r['fallbacks'][label]}")
        print(f"  median of per-step ratios other/this {r['ratio_median']:.3f}; max |du| "
              f"between the two {r['max_du']:.1e}")
        return
    if argv and argv[0] == "loop":
        masses = int(argv[1]) if len(argv) > 1 else 8
        steps = int(argv[2]) if len(argv) > 2 else 16
        out = loops(masses, steps, int(argv[3]) if len(argv) > 3 else None)
        print(f"{masses} masses, closed loops of {steps} steps taking turns (first step, "
              "which compiles, not timed; under load)")
        for label, r in out.items():
            print(f"  {label:<32} median step {1e3 * r['median']:8.2f} ms  worst "
                  f"{1e3 * r['worst']:8.2f} ms  max |du| vs old {r['max_du']:.1e}  "
                  f"fallbacks {r['fallbacks']}  row generation used: {r['rowgen']}"
                  + (f" (rows of the last solve: {r['rows']})" if r["rows"] else ""))
        return
    masses = int(argv[0]) if argv else 8
    steps = int(argv[1]) if len(argv) > 1 else 15
    preset = dict(resolve_target("fast-convex-rowgen").options["row_generation"])
    configs = [{"per_round": 1, "seed": "active"}, {"per_round": 1, "seed": "working"},
               {"per_round": 3, "seed": "working"}, preset]
    compiled, states = record(masses, steps)
    out = compare(compiled, states, configs)
    m0 = sum(m for kind, m in compiled.program.cones if kind == "zero")
    print(f"{masses} masses, {len(states)} states, {compiled.program.A.shape[0] - m0} "
          "inequality rows; times per solve under load, the configurations taking turns")
    for label, r in out.items():
        t = np.array(r["t"])
        line = f"  {label:<28} median {1e3 * np.median(t):8.2f} ms  worst {1e3 * t.max():8.2f} ms"
        if r["rounds"]:
            line += (f"  rounds {min(r['rounds'])}-{max(r['rounds'])} (median "
                     f"{np.median(r['rounds']):.0f}), final rows {min(r['rows'])}-"
                     f"{max(r['rows'])}, max |dv0| {max(r['dv'], default=np.nan):.1e}, "
                     f"max |dobj| {max(r['dobj'], default=np.nan):.1e}")
        print(line + f"  statuses {sorted(r['status'])}")


if __name__ == "__main__":
    main(sys.argv[1:])
