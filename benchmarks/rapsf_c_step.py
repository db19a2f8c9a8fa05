"""Algorithm 4.1 (the RAPSF) on the 3-mass chain: the emitted C step against the Python step,
interleaved on the same closed-loop states (docs/deploy_c.md, "Algorithm 4.1").

    PYTHONPATH=$PWD python benchmarks/rapsf_c_step.py [steps] [build_dir]

Builds the C once per source hash (``accelerate``'s cache, ~100 s the first time) and prints
the median and worst per-step time of: the Python controller on ``"convex-qp"`` (the chain
the C runs), the C step through :class:`~balustrade.codegen.CRAPSF` (with the Python
estimator update), the C call alone, and the Python controller on ``"fast-convex"``.
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

    def make(target: str) -> RAPSF:
        return RAPSF(system, X0, F, G, st.W, K, st.N, st.Theta0,
                     estimator=BoxUpdate(system, st.W, st.Theta0), target=target)

    py, fast = make("convex-qp"), make("fast-convex")
    c = accelerate(py, build_dir=build_dir)
    py.reset()
    rng = np.random.default_rng(3)
    theta = st.sample_theta(rng)
    times: dict[str, list[float]] = {"python convex-qp": [], "C step (with estimator)": [],
                                     "C call only": [], "python fast-convex": []}
    x, worst = st.x0.copy(), 0.0
    for k in range(steps):
        u_p = msd_performance(k, x, 3)
        t = time.perf_counter()
        u1, _ = py.step(x, u_p)
        times["python convex-qp"].append(time.perf_counter() - t)
        t = time.perf_counter()
        u2, info = c.step(x, u_p)
        times["C step (with estimator)"].append(time.perf_counter() - t)
        times["C call only"].append(info.solve_time)
        t = time.perf_counter()
        fast.step(x, u_p)
        times["python fast-convex"].append(time.perf_counter() - t)
        worst = max(worst, float(np.abs(u1 - u2).max()))
        x = system.step(x, u1, theta, rng.uniform(-1e-3, 1e-3, 6))
    for key, vals in times.items():
        print(f"{key:26s} median {1e3 * np.median(vals[1:]):8.2f} ms   "
              f"max {1e3 * np.max(vals[1:]):8.2f} ms")
    print(f"max |u_C - u_python| = {worst:.2e}")
    return times


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 150,
         sys.argv[2] if len(sys.argv) > 2 else None)
