"""Row generation against the full solve of (4.5) on the closed-loop states of the RAPSF bench
(docs/adaptive.md, "session 12: row generation")::

    PYTHONPATH=$PWD python -m benchmarks.rapsf_rowgen [masses] [steps] [per_round]

The closed loop of :class:`benchmarks.bench_rapsf.Loop` (design of ``reproduce msd-adaptive``,
box update, ``fast-convex``) runs ``steps`` steps and records the parameters of every solve of
the main horizon. Then, state by state in the loop's order, the same compiled problem is solved
whole (PIQP set up once, the default) and by row generation
(:mod:`balustrade.backends.row_generation`, seeded by the previous state's active rows), the
two taking turns. Reported: time per solve (median/worst), rounds, final rows, the largest
``|v_0|`` and objective differences, the statuses.
"""

from __future__ import annotations

import copy
import sys
import time

import numpy as np

from balustrade.backends.solution import Status
from balustrade.reproduce import msd_adaptive
from benchmarks.bench_rapsf import Loop


def record(masses: int, steps: int) -> tuple[object, list[dict]]:
    """The compiled main-horizon problem of the closed loop and the parameters of its solves."""
    d = msd_adaptive.design(masses)
    ctrl = msd_adaptive.adaptive_controller(d)
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


def compare(compiled: object, states: list[dict], per_round: int = 1) -> dict:
    """Full solve and row generation, interleaved state by state."""
    full = copy.copy(compiled)
    full.rowgen = None
    gen = copy.copy(compiled)
    gen.rowgen = compiled._row_generation({"per_round": per_round})
    for c in (full, gen):
        c.__dict__.pop("solve", None)  # the recording wrapper of record()
    t_full, t_gen, rounds, rows, dv, dobj, statuses = [], [], [], [], [], [], []
    for params in states:
        t0 = time.perf_counter()
        a = full.solve(params)
        t1 = time.perf_counter()
        b = gen.solve(params)
        t2 = time.perf_counter()
        t_full.append(t1 - t0)
        t_gen.append(t2 - t1)
        rounds.append(gen.rowgen.stats.rounds)
        rows.append(gen.rowgen.stats.rows)
        statuses.append((a.status.value, b.status.value))
        if a.status == Status.OPTIMAL and b.status == Status.OPTIMAL:
            dv.append(float(np.max(np.abs(a.primal["v"][:, 0] - b.primal["v"][:, 0]))))
            dobj.append(abs(a.objective - b.objective))
    m0 = sum(m for kind, m in compiled.program.cones if kind == "zero")
    return {"states": len(states), "ineq_rows": compiled.program.A.shape[0] - m0,
            "full_median": float(np.median(t_full)), "full_worst": float(np.max(t_full)),
            "gen_median": float(np.median(t_gen)), "gen_worst": float(np.max(t_gen)),
            "rounds": rounds, "rows": rows, "max_dv0": max(dv, default=np.nan),
            "max_dobj": max(dobj, default=np.nan),
            "statuses": sorted({f"{x}/{y}" for x, y in statuses})}


def main(argv: list[str]) -> None:
    masses = int(argv[0]) if argv else 8
    steps = int(argv[1]) if len(argv) > 1 else 15
    per_round = int(argv[2]) if len(argv) > 2 else 1
    compiled, states = record(masses, steps)
    r = compare(compiled, states, per_round)
    print(f"{masses} masses, {r['states']} states, {r['ineq_rows']} inequality rows, "
          f"{per_round} row(s) per violated group and round (under load)")
    print(f"  full solve      median {1e3 * r['full_median']:9.2f} ms  worst "
          f"{1e3 * r['full_worst']:9.2f} ms")
    print(f"  row generation  median {1e3 * r['gen_median']:9.2f} ms  worst "
          f"{1e3 * r['gen_worst']:9.2f} ms")
    print(f"  rounds {min(r['rounds'])}-{max(r['rounds'])} (median "
          f"{np.median(r['rounds']):.0f}); final rows {min(r['rows'])}-{max(r['rows'])} "
          f"(median {np.median(r['rows']):.0f})")
    print(f"  max |v0 diff| {r['max_dv0']:.2e}, max |objective diff| {r['max_dobj']:.2e}, "
          f"statuses (full/rowgen) {r['statuses']}")


if __name__ == "__main__":
    main(sys.argv[1:])
