"""``s_jr`` of a new ``Θ_k`` for a polytope ``𝕏₀`` whose vertices are not enumerated (5
masses: the contractive polytope in 10 states), old path against new, in one run
(docs/adaptive.md, "Session 15: the 5-mass step")::

    PYTHONPATH=$PWD python -m benchmarks.rapsf_s_lps [masses] [steps]

Two closed loops of the default controller with the same ``θ*`` and disturbances
(:class:`benchmarks.bench_rapsf.Loop`), taking turns every step (which goes first
alternates): ``old`` computes ``s_jr`` row by row (:func:`~balustrade.problems.rapsf.
s_constants`, one ``Polytope.support`` LP per row and vertex of ``Θ_k``, the code before
session 15), ``new`` in one solver run (:func:`balustrade.control.rapsf._s_from_lps`).
Prints per-step wall and CPU medians (first, compiling step not timed), the largest input
difference and the load average.
"""

from __future__ import annotations

import os
import sys
import time
from unittest import mock

import numpy as np

import balustrade.control.rapsf as rapsf_control
from balustrade.problems.rapsf import s_constants
from balustrade.reproduce import msd_adaptive
from benchmarks.bench_rapsf import Loop


def compare(masses: int, steps: int) -> dict:
    """Per-step wall and CPU times of the two paths and their largest input difference."""
    d = msd_adaptive.design(masses)
    loops = {k: Loop(d, msd_adaptive.adaptive_controller(d).step, steps)
             for k in ("old", "new")}
    cpu: dict[str, list[float]] = {k: [] for k in loops}

    def run(label: str, k: int) -> None:
        c0 = time.process_time()
        if label == "old":
            with mock.patch.object(rapsf_control, "_s_from_lps", s_constants):
                loops[label](k)
        else:
            loops[label](k)
        cpu[label].append(time.process_time() - c0)

    for k in range(steps):
        for label in (["old", "new"] if k % 2 else ["new", "old"]):
            run(label, k)
    du = float(np.max(np.abs(np.array(loops["old"].applied) - np.array(loops["new"].applied))))
    return {"wall": {k: np.array(v.times[1:]) for k, v in loops.items()},
            "cpu": {k: np.array(v[1:]) for k, v in cpu.items()}, "max_du": du,
            "fallbacks": {k: v.fallbacks for k, v in loops.items()}}


def main(argv: list[str]) -> None:
    masses = int(argv[0]) if argv else 5
    steps = int(argv[1]) if len(argv) > 1 else 60
    r = compare(masses, steps)
    print(f"{masses} masses, {steps} steps per loop, load average {os.getloadavg()}")
    for k in ("old", "new"):
        print(f"  {k}: step median {1e3 * np.median(r['wall'][k]):8.2f} ms wall, "
              f"{1e3 * np.median(r['cpu'][k]):8.2f} ms CPU; worst "
              f"{1e3 * r['wall'][k].max():8.2f} ms; fallbacks {r['fallbacks'][k]}")
    print(f"  max |u_old − u_new| = {r['max_du']:.1e}")


if __name__ == "__main__":
    main(sys.argv[1:])
