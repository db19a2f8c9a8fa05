"""Algorithm 4.1 (the RAPSF) on the 3-mass chain: the emitted C step against the Python step,
interleaved on the same closed-loop states (docs/deploy_c.md, "Algorithm 4.1").

    PYTHONPATH=$PWD python benchmarks/rapsf_c_step.py [steps] [build_dir]

Builds the C once per source hash (``accelerate``'s cache, ~100 s the first time; two
builds: cold and warm-started) and prints the median and worst per-step time of: the Python
controller on ``"convex-qp"`` (the chain the C runs), the C step through
:class:`~balustrade.codegen.CRAPSF` (with the Python estimator update), the C call alone,
the same three with ``warm_start=True`` ((4.5) from the previous step's solution after a
converged solve, in Python and in C), and the Python controller on ``"fast-convex"``; then
the largest input differences (C against Python, warm against cold, against
``fast-convex``).
"""

from __future__ import annotations

import sys
import time

import numpy as np

from balustrade.codegen import accelerate
from balustrade.control.rapsf import RAPSF
from balustrade.design.rapsf import contractive_polytope, robust_gain
from balustrade.estimate import BoxUpdate
from balustrade.models.msd import msd_chain, msd_performance, msd_setup
from balustrade.problems.rapsf import joint_constraints


def main(steps: int = 150, build_dir: str | None = None) -> dict[str, list[float]]:
    system, st = msd_chain(3), msd_setup(3)
    V = st.Theta0.vertices()
    F, G = joint_constraints(st.X, st.U)
    K = robust_gain(system, V, contraction=0.95)
    X0 = contractive_polytope(system, K, V, st.W, F, G)

    def make(target: str, warm: bool = False) -> RAPSF:
        return RAPSF(system, X0, F, G, st.W, K, st.N, st.Theta0,
                     estimator=BoxUpdate(system, st.W, st.Theta0), target=target,
                     warm_start=warm)

    py, fast = make("convex-qp"), make("fast-convex")
    py_w = make("convex-qp", warm=True)
    c = accelerate(py, build_dir=build_dir)
    c_w = accelerate(py_w, build_dir=build_dir)
    py.reset()
    py_w.reset()
    rng = np.random.default_rng(3)
    theta = st.sample_theta(rng)
    times: dict[str, list[float]] = {k: [] for k in (
        "python convex-qp", "C step (with estimator)", "C call only",
        "python convex-qp warm", "C step warm", "C call only warm", "python fast-convex")}
    worst = {"C vs python": 0.0, "C warm vs python warm": 0.0, "warm vs cold": 0.0,
             "cold vs fast-convex": 0.0}
    x = st.x0.copy()
    for k in range(steps):          # every path on the states of the cold Python loop
        u_p = msd_performance(k, x, 3)
        u = {}
        for key, ctrl, call in (("python convex-qp", py, None),
                                ("C step (with estimator)", c, "C call only"),
                                ("python convex-qp warm", py_w, None),
                                ("C step warm", c_w, "C call only warm"),
                                ("python fast-convex", fast, None)):
            t = time.perf_counter()
            u[key], info = ctrl.step(x, u_p)
            times[key].append(time.perf_counter() - t)
            if call is not None:
                times[call].append(info.solve_time)
        gaps = {"C vs python": ("C step (with estimator)", "python convex-qp"),
                "C warm vs python warm": ("C step warm", "python convex-qp warm"),
                "warm vs cold": ("python convex-qp warm", "python convex-qp"),
                "cold vs fast-convex": ("python convex-qp", "python fast-convex")}
        for label, (a, b) in gaps.items():
            worst[label] = max(worst[label], float(np.abs(u[a] - u[b]).max()))
        x = system.step(x, u["python convex-qp"], theta, rng.uniform(-1e-3, 1e-3, 6))
    for key, vals in times.items():
        print(f"{key:26s} median {1e3 * np.median(vals[1:]):8.2f} ms   "
              f"max {1e3 * np.max(vals[1:]):8.2f} ms")
    for label, gap in worst.items():
        print(f"max |u| difference, {label}: {gap:.2e}")
    return times


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 150,
         sys.argv[2] if len(sys.argv) > 2 else None)
