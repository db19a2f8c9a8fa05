"""RAPSF's default target against others on the same closed-loop states (docs/adaptive.md,
"Session 13: audit fixes")::

    PYTHONPATH=$PWD python -m benchmarks.rapsf_default_target [masses] [steps] [targets]

``targets`` is a comma list; ``default`` means ``RAPSF(...)`` without a ``target``. Every
controller (design of ``reproduce msd-adaptive``, box update) is stepped at the same state,
taking turns within each step; the state then moves with the first controller's input (θ* at
vertex 1 of Θ₀, uniform disturbances, seed 0). Printed per step: time, fallback, status; at
the end the median step (the first, with compilation, apart), the largest input difference
(over all steps, and over the steps where every controller solved (4.5) optimally) and
whether the fallbacks agreed at every step."""

from __future__ import annotations

import sys
import time

import numpy as np

from balustrade.control.rapsf import RAPSF
from balustrade.estimate import BoxUpdate
from balustrade.models.msd import msd_performance
from balustrade.problems.rapsf import model_matrices
from balustrade.reproduce import msd_adaptive as M


def run(n: int, steps: int, targets: list[str]) -> dict:
    d = M.design(n)
    s, sysm = d["setup"], d["system"]

    def make(t: str) -> RAPSF:
        kw = {} if t == "default" else {"target": t}
        return RAPSF(sysm, d["X0"], M.joint(d), None, s.W, d["K"], s.N, s.Theta0,
                     estimator=BoxUpdate(sysm, s.W, s.Theta0), **kw)

    ctrls = {t: make(t) for t in targets}
    print({t: c.target.name for t, c in ctrls.items()}, flush=True)
    rng = np.random.default_rng(0)
    A, B = model_matrices(sysm, s.Theta0.vertices()[1])
    x = np.zeros(2 * n)
    times: dict[str, list[float]] = {t: [] for t in targets}
    du, du_ok, same = 0.0, 0.0, True
    for k in range(steps):
        up, out = msd_performance(k, x, n), {}
        for t, c in ctrls.items():
            t0 = time.perf_counter()
            out[t] = c.step(x, up)
            times[t].append(time.perf_counter() - t0)
        us = [o[0] for o in out.values()]
        step_du = max(float(np.max(np.abs(u - us[0]))) for u in us)
        du = max(du, step_du)
        if all(o[1].fallback is None for o in out.values()):    # every (4.5) optimal
            du_ok = max(du_ok, step_du)
        same &= len({o[1].fallback for o in out.values()}) == 1
        print(k, {t: (round(1e3 * times[t][-1], 1), out[t][1].fallback, out[t][1].status)
                  for t in targets}, flush=True)
        x = A @ x + B @ us[0] + rng.uniform(-1e-3, 1e-3, 2 * n)
    res = {"median_ms": {t: 1e3 * float(np.median(v[1:] or v)) for t, v in times.items()},
           "first_ms": {t: 1e3 * v[0] for t, v in times.items()}, "max_du": du,
           "max_du_all_optimal": du_ok, "same_fallbacks": same}
    print(res, flush=True)
    return res


if __name__ == "__main__":
    a = sys.argv[1:]
    run(int(a[0]) if a else 3, int(a[1]) if len(a) > 1 else 30,
        (a[2] if len(a) > 2 else "default,fast-convex,exact").split(","))
