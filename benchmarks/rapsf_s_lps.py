"""``s_jr`` of a new ``Θ_k`` for a polytope ``𝕏₀`` whose vertices are not enumerated (5
masses: the contractive polytope in 10 states), old path against new, in one run
(docs/adaptive.md, "Session 15: the 5-mass step")::

    PYTHONPATH=$PWD python -m benchmarks.rapsf_s_lps [masses] [steps]

Two closed loops of the default controller with the same ``θ*`` and disturbances
(:class:`benchmarks.bench_rapsf.Loop`), taking turns every step (which goes first
alternates): ``old`` computes ``s_jr`` row by row (:func:`~balustrade.problems.rapsf.
s_constants`, one ``Polytope.support`` LP per row and vertex of ``Θ_k``, the code before
session 15), ``one run`` all of them as LPs in one solver run
(:func:`~balustrade.backends.lp.verified_supports`), ``new`` from the remembered vertices of
𝕏₀ where they verify and the rest in one run (:func:`balustrade.control.rapsf._s_from_lps`
with :class:`~balustrade.control.rapsf_supports.LearnedSupports`, the default). Prints
per-step wall and CPU medians (first, compiling step not timed), each path's largest input
difference from ``old``, the rows answered without an LP, and the load average.
"""

from __future__ import annotations

import os
import sys
import time
from unittest import mock

import numpy as np

import balustrade.control.rapsf as rapsf_control
from balustrade.control.rapsf import _s_from_lps as s_from_lps
from balustrade.problems.rapsf import s_constants
from balustrade.reproduce import msd_adaptive
from benchmarks.bench_rapsf import Loop

PATHS = ["old", "one run", "new"]


def compare(masses: int, steps: int) -> dict:
    """Per-step wall and CPU times of the two paths and their largest input difference."""
    d = msd_adaptive.design(masses)
    ctrls = {k: msd_adaptive.adaptive_controller(d) for k in PATHS}
    loops = {k: Loop(d, c.step, steps) for k, c in ctrls.items()}
    cpu: dict[str, list[float]] = {k: [] for k in loops}
    patched = {"old": lambda *a, **kw: s_constants(*a),
               "one run": lambda *a, **kw: s_from_lps(*a)}

    def run(label: str, k: int) -> None:
        c0 = time.process_time()
        if label in patched:
            with mock.patch.object(rapsf_control, "_s_from_lps", patched[label]):
                loops[label](k)
        else:
            loops[label](k)
        cpu[label].append(time.process_time() - c0)

    for k in range(steps):
        for label in np.roll(PATHS, k):
            run(str(label), k)
    old = np.array(loops["old"].applied)
    du = {k: float(np.max(np.abs(np.array(v.applied) - old))) for k, v in loops.items()}
    learned = ctrls["new"]._learned
    return {"wall": {k: np.array(v.times[1:]) for k, v in loops.items()},
            "cpu": {k: np.array(v[1:]) for k, v in cpu.items()}, "max_du": du,
            "fallbacks": {k: v.fallbacks for k, v in loops.items()},
            "reused": (learned.reused, learned.lps) if learned is not None else None}


def main(argv: list[str]) -> None:
    masses = int(argv[0]) if argv else 5
    steps = int(argv[1]) if len(argv) > 1 else 60
    r = compare(masses, steps)
    print(f"{masses} masses, {steps} steps per loop, load average {os.getloadavg()}")
    for k in PATHS:
        print(f"  {k:>7}: step median {1e3 * np.median(r['wall'][k]):8.2f} ms wall, "
              f"{1e3 * np.median(r['cpu'][k]):8.2f} ms CPU; worst "
              f"{1e3 * r['wall'][k].max():8.2f} ms; fallbacks {r['fallbacks'][k]}; "
              f"max |u − u_old| {r['max_du'][k]:.1e}")
    if r["reused"] is not None:
        print(f"  new: {r['reused'][0]} supports from remembered vertices, {r['reused'][1]} "
              "by LP")


if __name__ == "__main__":
    main(sys.argv[1:])
