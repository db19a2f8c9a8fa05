"""The real-time mode (issue #14 §5) on the pendulum PCBF filter (Section 7.5, N = 10): step
times of closed loops on the ``"real-time"`` preset (at most 3 SQP iterations per solve, no
retries) against the ``"fast-sqp"`` preset (100 iterations, retries ending with the
interior-point solver), runs interleaved (A, B, A, B, …) from the same seeded initial rates
and proposals. Reported per target: median, 99th percentile and worst step, in wall-clock and
process (CPU) time, the first step of each run excluded (it builds solver workspaces), the
largest iteration count of one solve and the number of truncated steps. ``ratio`` is the
fast-sqp worst CPU step over the real-time one (how many times shorter the real-time worst
case is); under load both worst cases carry scheduler and cache noise.
"""

from __future__ import annotations

import time

import numpy as np

from balustrade.control import PCBFSafetyFilter, simulate
from balustrade.design.terminal_cbf import synthesize_terminal_cbf
from balustrade.models.pendulum import pendulum, pendulum_setup

TARGETS = ("real-time", "fast-sqp")


class _Timed:
    """Records the process time of each step of the wrapped controller."""

    def __init__(self, inner: PCBFSafetyFilter):
        self.inner, self.cpu = inner, []

    def step(self, x: np.ndarray, u_p: np.ndarray):
        start = time.process_time()
        out = self.inner.step(x, u_p)
        self.cpu.append(time.process_time() - start)
        return out

    def reset(self) -> None:
        self.inner.reset()


def run(quick: bool = False) -> list[dict]:
    system, s = pendulum(), pendulum_setup()
    h_f = synthesize_terminal_cbf(system.A, system.B, s.X, s.U, delta_N=s.deltas[-1])
    ctls = {t: PCBFSafetyFilter.build(system, s.X, s.U, h_f, s.N, s.deltas, target=t)
            for t in TARGETS}
    rates = (-1.5, 0.75, 1.5) if quick else (-1.5, -0.75, 0.0, 0.75, 1.5, 1.2, -1.2, 0.4)
    steps = 100 if quick else 150
    rng = np.random.default_rng(0)
    acc = {t: {"wall": [], "cpu": [], "iters": 0, "truncated": 0, "psi": -np.inf}
           for t in TARGETS}
    for omega0 in rates:
        proposals = rng.uniform(-1.0, 5.0, size=steps)
        for t in TARGETS:  # interleaved: both targets on the same run, one after the other
            timed = _Timed(ctls[t])
            timed.reset()
            trace = simulate(system, timed, [0.0, omega0], steps,
                             proposal=lambda k, x, p=proposals: np.array([p[k]]),
                             keep_infos=True)
            a = acc[t]
            a["wall"].append(trace.step_times[1:])
            a["cpu"].append(np.asarray(timed.cpu[1:]))
            a["iters"] = max(a["iters"], max(sol.iterations for info in trace.infos
                                             for sol in info.solutions.values()))
            a["truncated"] += trace.n_truncated
            a["psi"] = max(a["psi"], float(np.max(trace.states[:, 0])))
    rows = []
    for t in TARGETS:
        wall, cpu = np.concatenate(acc[t]["wall"]), np.concatenate(acc[t]["cpu"])
        rows.append({"name": f"pendulum PCBF step, {t}", "median_s": float(np.median(wall)),
                     "p99_s": float(np.percentile(wall, 99)), "max_s": float(wall.max()),
                     "cpu_median_s": float(np.median(cpu)), "cpu_max_s": float(cpu.max()),
                     "max_iterations_per_solve": int(acc[t]["iters"]),
                     "truncated_steps": int(acc[t]["truncated"]), "steps": int(wall.size),
                     "max_psi": acc[t]["psi"]})
    rows[0]["baseline"] = "fast-sqp, worst CPU step"
    rows[0]["ratio"] = rows[1]["cpu_max_s"] / rows[0]["cpu_max_s"]
    return rows


if __name__ == "__main__":
    for row in run():
        print(row)
