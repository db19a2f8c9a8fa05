"""The horizon-free approximate PCBF (issue 5) against the two-problem PCBF step, same run.

* approximate filter step (Algorithm 7.5 without the shortcut: multi-start (7.6) then (7.5))
  with a 3 × 16 softplus network ``ĥ`` (random weights of the Figure 7.1 size: the solve
  time does not depend on the values), CasADi ``sqpmethod`` and IPOPT, against the PCBF
  step ((2.24) then (2.23), ``N = 10``) on the same solver;
* the certification test of Algorithm 7.5 (one evaluation of ``ĥ(f(x, u_p))``);
* Algorithm 8.7 (input grid of 11 candidates, one batched evaluation);
* sampling throughput for the pendulum (extended PCBF (7.7), IPOPT), warm-started line
  walks (Algorithm 7.6) against cold starts, per core.

Goals (reported, not asserted): approximate step ≥ 10× faster than the PCBF step;
certification < 20 µs; ≥ 500 samples/s per core with warm starts.
"""

from __future__ import annotations

import time

import numpy as np

from balustrade.backends import compile
from balustrade.control.approximate import ApproximatePCBFFilter, GridPCBFFilter
from balustrade.control.pcbf import PCBFSafetyFilter
from balustrade.learn.export import to_casadi
from balustrade.learn.sampler import IPOPT_SAMPLING, Evaluator, ProblemSpec, Seed
from balustrade.learn.train import MLPModel
from balustrade.models.pendulum import pendulum, pendulum_setup
from balustrade.problems.pcbf import pcbf_filter_problem, pcbf_slack_problem
from balustrade.problems.terminal_cbf import synthesize_terminal_cbf


def random_network(widths: tuple[int, ...] = (16, 16, 16), nx: int = 2,
                   seed: int = 0) -> MLPModel:
    """A softplus MLP with Glorot-scaled random weights, ``ĥ = x'Px − 1 + net`` shaped."""
    rng = np.random.default_rng(seed)
    sizes = (nx, *widths, 1)
    W = [rng.normal(0, np.sqrt(2 / (a + b)), (b, a)) for a, b in zip(sizes[:-1], sizes[1:])]
    b = [rng.normal(0, 0.1, n) for n in sizes[1:]]
    return MLPModel(W, b, np.zeros(nx), np.array([0.5, 1.5]))


def _median_time(fn, items, repeat: int = 1) -> float:
    times = []
    for _ in range(repeat):
        for item in items:
            t = time.perf_counter()
            fn(item)
            times.append(time.perf_counter() - t)
    return float(np.median(times))


def run(quick: bool = False) -> list[dict]:
    system, s = pendulum(), pendulum_setup()
    h_f = synthesize_terminal_cbf(system.A, system.B, s.X, s.U, delta_N=s.deltas[-1])
    args = (system, s.X, s.U, h_f, s.N, s.deltas)
    rng = np.random.default_rng(0)
    states = rng.uniform(s.X.lb, s.X.ub, (20 if quick else 200, 2))
    u_p = np.array([2.0])
    h_hat = to_casadi(random_network())
    rows = []
    for solver in ("sqpmethod", "ipopt"):
        opts = IPOPT_SAMPLING if solver == "ipopt" else None
        pcbf = PCBFSafetyFilter(
            compile(pcbf_slack_problem(*args, alpha_f=s.alpha_f, slack_norm=1), "casadi",
                    solver, opts),
            compile(pcbf_filter_problem(*args), "casadi", solver, opts), s.U)
        approx = ApproximatePCBFFilter(system, s.U, h_hat, rho=0.5, solver=solver,
                                       certify=False)
        t_pcbf = _median_time(lambda x, f=pcbf: (f.reset(), f.step(x, u_p)), states)
        both = ApproximatePCBFFilter(system, s.U, h_hat, rho=0.5, solver=solver,
                                     certify=False, exact_shortcut=False)
        t_approx = _median_time(lambda x, f=approx: f.step(x, u_p), states)
        t_both = _median_time(lambda x, f=both: f.step(x, u_p), states)
        rows.append({"name": f"PCBF step (2.24)+(2.23), N=10, {solver}", "median_s": t_pcbf})
        rows.append({"name": f"approximate step (7.6)+(7.5), 3x16 net, {solver}",
                     "median_s": t_approx, "baseline": f"PCBF step ({solver})",
                     "ratio": t_pcbf / t_approx,
                     "u_p_feasible_share": round(approx.n_proposal_feasible
                                                 / max(approx.n_solved, 1), 2)})
        rows.append({"name": f"approximate step, always both solves, {solver}",
                     "median_s": t_both, "baseline": f"PCBF step ({solver})",
                     "ratio": t_pcbf / t_both})
    cert = ApproximatePCBFFilter(system, s.U, h_hat, solver="sqpmethod")
    t_cert = _median_time(lambda x: cert.certifies(x, u_p), states, repeat=20)
    rows.append({"name": "certification test (Alg. 7.5 line 4)", "median_s": t_cert,
                 "goal_s": 20e-6})
    grid = GridPCBFFilter(system, s.U, h_hat, half_width=0.5, spacing=0.1)
    t_grid = _median_time(lambda x: grid.step(x, u_p), states, repeat=5)
    rows.append({"name": "Algorithm 8.7 grid filter step (11 inputs)", "median_s": t_grid})

    # sampling throughput: line walks of Algorithm 7.6 (d = 0.01) through S_PB and out
    problems = ProblemSpec.of("pendulum", solver="ipopt").build()
    goals = [np.array([0.8, 2.0]), np.array([-0.7, 2.5]), np.array([0.3, -3.0])]
    if quick:
        goals = goals[:1]
    rates = {}
    for warm in (True, False):
        ev = Evaluator(problems, warm=warm)
        n, t = 0, time.perf_counter()
        for g in goals:
            x0 = np.zeros(2)
            line, _ = ev.walk(x0, g, 0.01, Seed(x0))
            n += len(line)
        rates[warm] = n / (time.perf_counter() - t)
    rows.append({"name": "sampling h (7.7), warm-started line walks, per core",
                 "median_s": 1.0 / rates[True], "samples_per_s": round(rates[True], 1),
                 "baseline": "cold starts", "ratio": rates[True] / rates[False]})
    rows.append({"name": "sampling h (7.7), cold starts, per core",
                 "median_s": 1.0 / rates[False], "samples_per_s": round(rates[False], 1)})
    return rows


if __name__ == "__main__":  # pragma: no cover
    for row in run(quick=True):
        print(row)
