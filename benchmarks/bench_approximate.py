"""The horizon-free approximate PCBF (issue 5) against the two-problem PCBF step, same run.

* approximate filter step (Algorithm 7.5 without the shortcut: multi-start (7.6), then the
  exact ``u_p``-feasible shortcut or (7.5)) against the PCBF step ((2.24) then (2.23),
  ``N = 10``) on the same solver, both through CasADi's SX virtual machine from Python
  (no JIT, no generated C). Two workloads for ``ĥ``:

  - ``net``: a 3 × 16 softplus network with random weights (the Figure 7.1 size; the
    solve time does not depend on the values). For ~98 % of the states the best screened
    start of (7.6) is a vertex of ``U`` where the gradient points out (the solver is
    skipped, exactly), and ``u_p`` meets the decrease of (7.5) (no (7.5) solve);
  - ``bowl``: ``ĥ = h_f + 0.1·net`` (the terminal CBF plus the network): interior (7.6)
    minimizers, (7.5) solved at ~75 % of the states — the solver-bound case;

  the columns ``kkt_vertex_share`` / ``u_p_feasible_share`` say which path was taken;
* the PCBF step's two ``nlpsol`` calls alone, through preallocated buffers (a lower bound
  for any Python PCBF step on this path: the like-for-like baseline for buffered calls);
* the certification test of Algorithm 7.5 (``u_p ∈ U`` and one evaluation of
  ``ĥ(f(x, u_p))``, buffered), against a plain ``Function.__call__`` of ``ĥ ∘ f``;
* Algorithm 8.7 (input grid of 11 candidates, one batched evaluation);
* sampling throughput for the pendulum (extended PCBF (7.7)), warm-started line walks
  (Algorithm 7.6, ``d = 0.01``) against cold starts, per core: ``sqpmethod`` warm + IPOPT
  cold (the sampler's default) and IPOPT only.

Goals (reported, not asserted): approximate step ≥ 10× faster than the PCBF step;
certification < 20 µs; ≥ 500 samples/s per core with warm starts.
"""

from __future__ import annotations

import time

import casadi as ca
import numpy as np

from balustrade.backends import compile
from balustrade.control.approximate import ApproximatePCBFFilter, GridPCBFFilter
from balustrade.control.pcbf import PCBFSafetyFilter
from balustrade.learn.export import to_casadi
from balustrade.learn.sampler import IPOPT_SAMPLING, Evaluator, ProblemSpec, Seed
from balustrade.learn.train import MLPModel
from balustrade.models.pendulum import pendulum, pendulum_setup
from balustrade.problems.approximate import FastNLP
from balustrade.problems.pcbf import pcbf_filter_problem, pcbf_slack_problem
from balustrade.problems.terminal_cbf import synthesize_terminal_cbf


def random_network(widths: tuple[int, ...] = (16, 16, 16), nx: int = 2,
                   seed: int = 0) -> MLPModel:
    """A softplus MLP with Glorot-scaled random weights (inputs scaled by (0.5, 1.5))."""
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


def _raw_pcbf_step(slack, filt) -> callable:
    """The PCBF step's two solver calls through :class:`FastNLP` buffers (cold (2.24),
    (2.23) from the (2.24) primal), with the parameter packing they need."""
    fs, ff = FastNLP(slack), FastNLP(filt)

    def step(x: np.ndarray, u_p: np.ndarray) -> None:
        out = fs.solve(x, {})
        if out is None:
            return
        w = out[0]
        v = slack.ocp.unpack_variables(w[: slack.n_user])
        p = filt.ocp.pack_parameters({"x0": x, "u_p": u_p, "xi": np.maximum(v["xi"], 0.0),
                                      "xi_N": np.maximum(v["xi_N"], 0.0)})
        ff.solve(p, {"x": v["x"], "u": v["u"]})

    return step


def _approx_rows(label: str, h_hat, states, u_p, solver: str, t_pcbf: float,
                 system, U) -> list[dict]:
    approx = ApproximatePCBFFilter(system, U, h_hat, rho=0.5, solver=solver, certify=False)
    both = ApproximatePCBFFilter(system, U, h_hat, rho=0.5, solver=solver, certify=False,
                                 exact_shortcut=False)
    approx.step(states[0], u_p)
    both.step(states[0], u_p)  # build the FastNLP solvers outside the timing
    approx.reset()
    kkt = sum(approx.decrease.solve(x, u_p).n_kkt_starts > 0 for x in states)
    t_approx = _median_time(lambda x, f=approx: f.step(x, u_p), states)
    t_both = _median_time(lambda x, f=both: f.step(x, u_p), states)
    return [{"name": f"approximate step (7.6)+(7.5), {label}, {solver}",
             "median_s": t_approx, "baseline": f"PCBF step ({solver})",
             "ratio": t_pcbf / t_approx,
             "kkt_vertex_share": round(kkt / len(states), 2),
             "u_p_feasible_share": round(approx.n_proposal_feasible
                                         / max(approx.n_solved, 1), 2)},
            {"name": f"approximate step, always both solves, {label}, {solver}",
             "median_s": t_both, "baseline": f"PCBF step ({solver})",
             "ratio": t_pcbf / t_both}]


def run(quick: bool = False) -> list[dict]:
    system, s = pendulum(), pendulum_setup()
    h_f = synthesize_terminal_cbf(system.A, system.B, s.X, s.U, delta_N=s.deltas[-1])
    args = (system, s.X, s.U, h_f, s.N, s.deltas)
    rng = np.random.default_rng(0)
    states = rng.uniform(s.X.lb, s.X.ub, (20 if quick else 200, 2))
    u_p = np.array([2.0])
    net = to_casadi(random_network())
    xs = ca.SX.sym("x", 2)
    bowl = ca.Function("bowl", [xs], [h_f(xs) + 0.1 * net(xs)])
    rows = []
    for solver in ("sqpmethod", "ipopt"):
        opts = IPOPT_SAMPLING if solver == "ipopt" else None
        slack = compile(pcbf_slack_problem(*args, alpha_f=s.alpha_f, slack_norm=1), "casadi",
                        solver, opts)
        filt = compile(pcbf_filter_problem(*args), "casadi", solver, opts)
        pcbf = PCBFSafetyFilter(slack, filt, s.U)
        t_pcbf = _median_time(lambda x, f=pcbf: (f.reset(), f.step(x, u_p)), states)
        rows.append({"name": f"PCBF step (2.24)+(2.23), N=10, {solver}", "median_s": t_pcbf})
        if solver == "sqpmethod":
            raw = _raw_pcbf_step(slack, filt)
            t_raw = _median_time(lambda x, r=raw: r(x, u_p), states)
            rows.append({"name": "PCBF step, the two nlpsol calls only (buffered), sqpmethod",
                         "median_s": t_raw})
        rows += _approx_rows("net", net, states, u_p, solver, t_pcbf, system, s.U)
        if solver == "sqpmethod":
            rows[-2]["ratio_vs_raw_pcbf"] = round(t_raw / rows[-2]["median_s"], 1)
            rows += _approx_rows("bowl", bowl, states, u_p, solver, t_pcbf, system, s.U)
            rows[-2]["ratio_vs_raw_pcbf"] = round(t_raw / rows[-2]["median_s"], 1)
    cert = ApproximatePCBFFilter(system, s.U, net, solver="sqpmethod")
    t_cert = _median_time(lambda x: cert.certifies(x, u_p), states, repeat=20)
    h_next = cert._h_next
    t_call = _median_time(lambda x: bool(np.all(np.abs(u_p) <= 3.0)
                                         and float(h_next(x, u_p)) <= 0.0), states, repeat=20)
    rows.append({"name": "certification test via Function.__call__ (reference)",
                 "median_s": t_call})
    rows.append({"name": "certification test (Alg. 7.5 line 4), buffered", "median_s": t_cert,
                 "baseline": "Function.__call__", "ratio": t_call / t_cert, "goal_s": 20e-6})
    grid = GridPCBFFilter(system, s.U, net, half_width=0.5, spacing=0.1)
    t_grid = _median_time(lambda x: grid.step(x, u_p), states, repeat=5)
    rows.append({"name": "Algorithm 8.7 grid filter step (11 inputs)", "median_s": t_grid})

    # sampling throughput: line walks of Algorithm 7.6 (d = 0.01) through S_PB and out
    goals = [np.array([0.8, 2.0]), np.array([-0.7, 2.5]), np.array([0.3, -3.0])]
    if quick:
        goals = goals[:1]
    for solver, label in (("sqpmethod", "sqpmethod warm / IPOPT cold"), ("ipopt", "IPOPT")):
        problems = ProblemSpec.of("pendulum", solver=solver).build()
        rates = {}
        for warm in (True, False):
            ev = Evaluator(problems, warm=warm)
            n, t = 0, time.perf_counter()
            for g in goals:
                x0 = np.zeros(2)
                line, _ = ev.walk(x0, g, 0.01, Seed(x0))
                n += len(line)
            rates[warm] = n / (time.perf_counter() - t)
        rows.append({"name": f"sampling h (7.7), warm-started line walks, {label}, per core",
                     "median_s": 1.0 / rates[True], "samples_per_s": round(rates[True], 1),
                     "baseline": "cold starts (IPOPT)", "ratio": rates[True] / rates[False]})
        rows.append({"name": f"sampling h (7.7), cold starts (IPOPT), per core [{solver}]",
                     "median_s": 1.0 / rates[False], "samples_per_s": round(rates[False], 1)})
    return rows


if __name__ == "__main__":  # pragma: no cover
    for row in run(quick=True):
        print(row)
