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
from balustrade.backends.casadi_fast import FastNLP
from balustrade.control.approximate import ApproximatePCBFFilter, GridPCBFFilter
from balustrade.control.pcbf import PCBFSafetyFilter
from balustrade.design.terminal_cbf import synthesize_terminal_cbf
from balustrade.learn.export import to_casadi
from balustrade.learn.sampler import Evaluator, ProblemSpec, Seed
from balustrade.learn.train import MLPModel
from balustrade.models.pendulum import pendulum, pendulum_setup
from balustrade.problems.pcbf import pcbf_filter_problem, pcbf_slack_problem
from benchmarks._timing import interleaved


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
        v = slack.ocp.unpack_variables(out[0][: slack.layout.user_size])
        p = filt.ocp.pack_parameters({"x0": x, "u_p": u_p, "xi": np.maximum(v["xi"], 0.0),
                                      "xi_N": np.maximum(v["xi_N"], 0.0)})
        ff.solve(p, {"x": v["x"], "u": v["u"]})

    return step


#: the targets behind the solver names of the rows (row names unchanged across versions):
#: Algorithm 7.5, the PCBF pair, the sampler
FILTER_TARGET = {"sqpmethod": "fast-sqp", "ipopt": "exact"}
PCBF_TARGET = {"sqpmethod": "fast-sqp", "ipopt": "sampling-cold"}


def _filters(h_hat, solver: str, system, U, states, u_p) -> dict:
    out = {}
    for both in (False, True):
        f = ApproximatePCBFFilter(system, U, h_hat, rho=0.5, target=FILTER_TARGET[solver],
                                  certify=False,
                                  exact_shortcut=not both)
        f.step(states[0], u_p)  # warm-up call outside the timing
        f.reset()
        out[both] = f
    return out


def run(quick: bool = False) -> list[dict]:
    system, s = pendulum(), pendulum_setup()
    h_f = synthesize_terminal_cbf(system.A, system.B, s.X, s.U, delta_N=s.deltas[-1])
    args = (system, s.X, s.U, h_f, s.N, s.deltas)
    rng = np.random.default_rng(0)
    states = rng.uniform(s.X.lb, s.X.ub, (20 if quick else 200, 2))
    u_p = np.array([2.0])
    net = to_casadi(random_network())
    xs = ca.SX.sym("x", 2)
    workloads = {"net": net, "bowl": ca.Function("bowl", [xs], [h_f(xs) + 0.1 * net(xs)])}
    rows = []
    for solver in ("sqpmethod", "ipopt"):
        slack = compile(pcbf_slack_problem(*args, alpha_f=s.alpha_f, slack_norm=1),
                        PCBF_TARGET[solver])
        filt = compile(pcbf_filter_problem(*args), PCBF_TARGET[solver])
        pcbf = PCBFSafetyFilter(slack, filt, s.U)
        fns = {"pcbf": lambda x, f=pcbf: (f.reset(), f.step(x, u_p))}
        if solver == "sqpmethod":
            raw = _raw_pcbf_step(slack, filt)
            fns["raw"] = lambda x, r=raw: r(x, u_p)
        filters = {}
        for label, h_hat in workloads.items():
            if solver == "ipopt" and label == "bowl":
                continue
            filters[label] = _filters(h_hat, solver, system, s.U, states, u_p)
            for both, f in filters[label].items():
                fns[(label, both)] = lambda x, f=f: f.step(x, u_p)
        t = interleaved(fns, states)
        rows.append({"name": f"PCBF step (2.24)+(2.23), N=10, {solver}", "median_s": t["pcbf"]})
        if "raw" in t:
            rows.append({"name": "PCBF step, the two nlpsol calls only (buffered), sqpmethod",
                         "median_s": t["raw"]})
        for label, fs in filters.items():
            f = fs[False]
            kkt = sum(f.decrease.solve(x, u_p).n_kkt_starts > 0 for x in states)
            row = {"name": f"approximate step (7.6)+(7.5), {label}, {solver}",
                   "median_s": t[(label, False)], "baseline": f"PCBF step ({solver})",
                   "ratio": t["pcbf"] / t[(label, False)],
                   "kkt_vertex_share": round(kkt / len(states), 2),
                   "u_p_feasible_share": round(f.n_proposal_feasible / max(f.n_solved, 1), 2)}
            if "raw" in t:
                row["ratio_vs_raw_pcbf"] = round(t["raw"] / t[(label, False)], 1)
            rows.append(row)
            rows.append({"name": f"approximate step, always both solves, {label}, {solver}",
                         "median_s": t[(label, True)], "baseline": f"PCBF step ({solver})",
                         "ratio": t["pcbf"] / t[(label, True)]})
    cert = ApproximatePCBFFilter(system, s.U, net, target="fast-sqp")
    h_next = cert._h_next
    t = interleaved({"cert": lambda x: cert.certifies(x, u_p),
                      "call": lambda x: bool(np.all(np.abs(u_p) <= 3.0)
                                             and float(h_next(x, u_p)) <= 0.0)},
                     states, repeat=20)
    rows.append({"name": "certification test via Function.__call__ (reference)",
                 "median_s": t["call"]})
    rows.append({"name": "certification test (Alg. 7.5 line 4), buffered",
                 "median_s": t["cert"], "baseline": "Function.__call__",
                 "ratio": t["call"] / t["cert"], "goal_s": 20e-6})
    grid = GridPCBFFilter(system, s.U, net, half_width=0.5, spacing=0.1)
    t_grid = _median_time(lambda x: grid.step(x, u_p), states, repeat=5)
    rows.append({"name": "Algorithm 8.7 grid filter step (11 inputs)", "median_s": t_grid})

    # sampling throughput: line walks of Algorithm 7.6 (d = 0.01) through S_PB and out,
    # the modes interleaved line by line
    goals = [np.array([0.8, 2.0]), np.array([-0.7, 2.5]), np.array([0.3, -3.0])]
    if quick:
        goals = goals[:1]
    sqp = ProblemSpec.of("pendulum", target="fast-sqp").build()
    ipopt = ProblemSpec.of("pendulum", target="exact").build()
    modes = {"sqp": Evaluator(sqp, warm=True), "ipopt": Evaluator(ipopt, warm=True),
             "cold": Evaluator(ipopt, warm=False)}
    count = {k: 0 for k in modes}
    spent = {k: 0.0 for k in modes}
    for g in goals:
        for k, ev in modes.items():
            x0 = np.zeros(2)
            t0 = time.perf_counter()
            line, _ = ev.walk(x0, g, 0.01, Seed(x0))
            spent[k] += time.perf_counter() - t0
            count[k] += len(line)
    rate = {k: count[k] / spent[k] for k in modes}
    rows.append({"name": "sampling h (7.7), warm line walks, sqpmethod warm / IPOPT cold, "
                 "per core", "median_s": 1.0 / rate["sqp"],
                 "samples_per_s": round(rate["sqp"], 1), "baseline": "cold starts (IPOPT)",
                 "ratio": rate["sqp"] / rate["cold"]})
    rows.append({"name": "sampling h (7.7), warm line walks, IPOPT only, per core",
                 "median_s": 1.0 / rate["ipopt"], "samples_per_s": round(rate["ipopt"], 1),
                 "baseline": "cold starts (IPOPT)", "ratio": rate["ipopt"] / rate["cold"]})
    rows.append({"name": "sampling h (7.7), cold starts (IPOPT), per core",
                 "median_s": 1.0 / rate["cold"], "samples_per_s": round(rate["cold"], 1)})
    return rows


if __name__ == "__main__":  # pragma: no cover
    for row in run(quick=True):
        print(row)
