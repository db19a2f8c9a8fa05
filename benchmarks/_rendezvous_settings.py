"""Candidate Clarabel settings for the rendezvous (issue #14, "≤ 10 ms per step"): the
balustrade default against the hand-written baseline (:mod:`benchmarks._clarabel_direct`),
each with Clarabel's settings as they are and with a candidate change, timed interleaved on
the states of ``bench_robust`` (state by state, path after path; paired ratios to the
baseline with its default settings).

Run (not part of ``balustrade bench``; ~2–4 min at N = 200 under load)::

    PYTHONPATH=$PWD python -m benchmarks._rendezvous_settings [--passes 2] [--N 200]

The candidate (``CANDIDATE``): iterative refinement of the KKT solves stopped at 1e-10
instead of Clarabel's 1e-13/1e-12 — the termination tolerances (gap, feasibility) are not
changed, so a "Solved" is judged by the same criteria; per iteration Clarabel spends ~2/3 of
its time in the KKT solves (with the refinement steps) and ~1/3 in the factorization.
Reported per path: median per step, iterations, statuses, and the largest differences of
the applied input and ``h_r``/fuel from the same path with the default settings.

This module names Clarabel's options because it is benchmark code measuring them, not part
of the library.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from balustrade.backends import resolve_target
from balustrade.reproduce.rendezvous import controllers, design
from benchmarks import _clarabel_direct as hw
from benchmarks.bench_robust import closed_loop_states

#: the candidate change of Clarabel's settings
CANDIDATE = {"iterative_refinement_reltol": 1e-10, "iterative_refinement_abstol": 1e-10}


def _handwritten(data: hw.RendezvousData, options: dict) -> hw.DirectRendezvous:
    """The baseline with ``options`` added to its settings (module-level settings factory
    swapped while it is built)."""
    plain = hw._settings

    def settings():
        st = plain()
        for key, value in options.items():
            setattr(st, key, value)
        return st

    hw._settings = settings
    try:
        return hw.DirectRendezvous(data)
    finally:
        hw._settings = plain


def main(N: int = 200, passes: int = 2, n_states: int = 12) -> dict:
    d = design(N, 40)
    data = hw.RendezvousData.from_design(d)
    base = {"default": hw.DirectRendezvous(data), "candidate": _handwritten(data, CANDIDATE)}
    states = closed_loop_states(d, base["default"], n_states + 1)
    target = resolve_target("fast-convex")
    ours = {}
    for label, tgt in (("default", None), ("candidate", target.with_options(CANDIDATE))):
        ctls = controllers(d, (0.9,), target=tgt, record_h_r=False)
        ours[label] = (ctls["robust"], ctls["mo_rho0.9"])
    t: dict = {}
    out: dict = {}
    for _ in range(passes):
        for robust, mo in ours.values():
            robust.reset()
            mo.reset()
        for j, x in enumerate(states):
            bound = None
            for label, (robust, mo) in ours.items():
                for alg, ctl in (("5.2", robust), ("6.4", mo)):
                    start = time.perf_counter()
                    u, info = ctl.step(x, np.zeros(3))
                    el = time.perf_counter() - start
                    its = sum(s.iterations for s in info.solutions.values())
                    ok = info.status == "ok" and not info.fallback
                    value = info.values.get("h_r", info.values.get("h_tilde", np.nan))
                    if alg == "6.4" and label == "default":
                        bound = info.values["bound"]
                    if j:
                        t.setdefault(("balustrade", label, alg), []).append((el, its, ok))
                        out.setdefault(("balustrade", label, alg), []).append((u, value))
            for label, prob in base.items():
                for alg in ("5.2", "6.4"):
                    start = time.perf_counter()
                    res = prob.alg52(x) if alg == "5.2" else prob.alg64(x, bound)
                    el = time.perf_counter() - start
                    if j:
                        t.setdefault(("hand-written", label, alg), []).append(
                            (el, prob.last_iterations, res[0]))
                        out.setdefault(("hand-written", label, alg), []).append(
                            (res[1], res[2]))
    rows = {}
    for alg in ("5.2", "6.4"):
        ref = np.array([s[0] for s in t[("hand-written", "default", alg)]])
        for key in sorted(k for k in t if k[2] == alg):
            samples = t[key]
            el = np.array([s[0] for s in samples])
            same = out[(key[0], "default", alg)]
            du = max(float(np.max(np.abs(np.asarray(a[0]) - np.asarray(b[0]))))
                     for a, b in zip(out[key], same, strict=True))
            dv = max(abs(float(a[1]) - float(b[1])) for a, b in zip(out[key], same, strict=True))
            rows[key] = {"median_ms": round(1e3 * float(np.median(el)), 2),
                         "paired_vs_handwritten_default": round(float(np.median(el / ref)), 3),
                         "iterations": int(sum(s[1] for s in samples)),
                         "failed": int(sum(not s[2] for s in samples)),
                         "max_du_vs_default": float(f"{du:.2g}"),
                         "max_dvalue_vs_default": float(f"{dv:.2g}")}
            print(f"Alg {alg} {key[0]:12s} {key[1]:9s}", rows[key], flush=True)
    return rows


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--N", type=int, default=200)
    ap.add_argument("--passes", type=int, default=2)
    args = ap.parse_args()
    main(args.N, args.passes)
