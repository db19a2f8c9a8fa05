"""Issue #12 check (docs/engines.md, "Infeasible" verdicts): the QP (4.5) of the 8-mass RAPSF
on ``fast-convex`` (PIQP) vs ``fast-convex-conic`` (Clarabel) at the parameters of the
reproduction's own closed loop (seed 0), same compiled problem. Not part of ``balustrade
bench`` (minutes per step under load)::

    PYTHONPATH=$PWD python -m benchmarks._verdicts_rapsf8 35
"""

from __future__ import annotations

import sys

import numpy as np

from balustrade.backends import compile
from balustrade.models.msd import msd_performance
from balustrade.reproduce import msd_adaptive as M


def recorded_loop(steps: int) -> tuple[object, list]:
    """The adaptive controller after ``steps`` closed-loop steps and the parameters of every
    (4.5) solve (``(step, key, params)``; the first solve, inside the first compile, is
    not recorded)."""
    d = M.design(8, 150)
    s = d["setup"]
    rng = np.random.default_rng(0)
    theta = s.sample_theta(rng)
    ws = rng.uniform(s.W.lb, s.W.ub, size=(150, 16))
    ctrl = M.adaptive_controller(d)
    ctrl.reset()
    records: list = []
    x = np.array(s.x0, dtype=float)
    for k in range(steps):
        for key, c in list(ctrl._compiled.items()):
            if not getattr(c, "_recorded", False):
                def rec(params=None, warm_start=None, _orig=c.solve, _key=key):
                    records.append((len(records), _key, {n: np.array(v, dtype=float)
                                                         for n, v in params.items()}))
                    return _orig(params, warm_start)
                c.solve, c._recorded = rec, True
        u, _ = ctrl.step(x, msd_performance(k, x, 8))
        x = d["system"].step(x, u, theta, ws[k])
    return ctrl, records


def main(argv: list[str]) -> int:
    steps = int(argv[0]) if argv else 35
    ctrl, records = recorded_loop(steps)
    key = records[-1][1]
    prob = ctrl._problem(key[0], n_vertices=key[1])
    piqp, conic = compile(prob, "fast-convex"), compile(prob, "fast-convex-conic")
    counts: dict = {}
    for i, k, params in records:
        if k != key:
            continue
        a, c = piqp.solve(params), conic.solve(params)
        pair = (str(a.status), str(c.status))
        counts[pair] = counts.get(pair, 0) + 1
        print(f"solve {i}: PIQP {a.status} {a.objective:.6g} | Clarabel {c.status} "
              f"{c.objective:.6g} [{c.message}]", flush=True)
    print({f"PIQP {p} / Clarabel {q}": n for (p, q), n in counts.items()})
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
