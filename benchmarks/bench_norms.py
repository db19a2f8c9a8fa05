"""IPOPT time per solve of the slack problem (2.24) with the slack norms 1, 2 and ∞ on a
nonlinear lane-keeping PCBF: the kinematic bicycle of Section 8.2 (4 states, 2 inputs),
``N = 50``, the lane box ``X``, terminal CBF around ``x_s = (0, 0, 1.1, 0)``, ``α_f = 10⁶``,
``Δ_i = 10⁻⁴ i``, from 20 seeded states inside and outside the lane (issue #12).

``norm2 (textbook epigraph)`` is the same problem with ``‖ξ_i‖₂`` written as
``ξ_iᵀξ_i − t_i² <= 0``, ``t_i >= 0`` by hand — the lowering the CasADi backend used before
issue #12 (degenerate at ``ξ_i = 0``). ``ratio`` is, as in every benchmark, the baseline's
median time over the row's (< 1: the row is slower): the 2- and ∞-norm rows against the
1-norm, the textbook row against the backend's 2-norm. All problems are solved state by
state in turn (interleaved). ``quick`` uses 6 states. ``median_ms_per_iter``: time per IPOPT
iteration.

Where the 2-norm's extra time goes (session 8, 20 states, interleaved, under load): about
1.4× the IPOPT iterations of the 1-norm (46 vs 32.5: a longer tail at ``μ <= 1e-13``, where
the slack columns sit at the cone's apex and the perspective row's curvature grows like
``1/t``) times about 1.4× the time per iteration (the KKT system is larger by the 50
epigraph variables, 50 cone rows and 400 cuts ``ξ_ij <= t_i``; the 1-norm of ``ξ >= 0`` is
linear and adds nothing). Tried and rejected: one aggregate cut ``1ᵀξ_i <= √8·t_i`` per
stage (the 1-norm's time per iteration, but IPOPT then stopped at its acceptable level on
5 of 20 states and left ``5.6e-7`` where ``h_PB ≈ 4e-11``; with sqpmethod it stopped
"optimal" 8.6e-4 above the optimum on a pendulum state), no cuts (a wrong value, 550,
reported feasible), the variational form ``½(ξᵀξ/t + t)`` in the cost (62 iterations),
``ξᵀξ/(t + ε)`` instead of ``ξᵀξ/max(t, ε)`` and a positive initial ``t`` (different local
minima and inexact stops on this nonconvex problem), dropping ``t >= 0`` (62 iterations).
The squared norm ``Σ‖ξ_i‖₂²`` is not an exact rewrite: it is not positively homogeneous,
so it moves the trade-off with ``α_f ξ_N`` and between stages and gives another ``h_PB``.
"""

from __future__ import annotations

import time
import warnings

import casadi as ca
import numpy as np

from balustrade.backends import compile
from balustrade.dsl.ocp import OCP
from balustrade.examples.bicycle import bicycle_design
from balustrade.models.bicycle import DEG
from balustrade.problems.pcbf import pcbf_slack_problem

N = 50


def states(n: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [np.array([rng.uniform(-0.3, 0.3), rng.uniform(-40, 40) * DEG,
                      rng.uniform(0.6, 1.3), rng.uniform(-30, 30) * DEG]) for _ in range(n)]


def textbook_norm2(ocp: OCP, alpha_f: float) -> OCP:
    """Replace ``Σ_i ‖ξ_i‖₂`` of (2.24) by ``Σ_i t_i`` with ``ξ_iᵀξ_i − t_i² <= 0``."""
    xi = ocp.variables["xi"].sym
    t = ocp.variable("t_norm", xi.shape[1], lb=0.0, role="slack")
    for i in range(xi.shape[1]):
        ocp.le(ca.sumsqr(xi[:, i]) - t[i] ** 2, name=f"soc{i}")
    ocp.minimize(alpha_f * ocp.variables["xi_N"].sym + ca.sum1(t))
    return ocp


def _time(compiled: dict, xs: list[np.ndarray]) -> dict[str, dict]:
    """Solve every state with every compiled problem, interleaved (state by state, each
    problem in turn: load on the machine hits all of them alike); per problem label the
    median and worst time, iterations, time per iteration, statuses and values."""
    runs = {label: ([], [], {}, []) for label in compiled}
    for x in xs:
        for label, c in compiled.items():
            times, iters, statuses, values = runs[label]
            start = time.perf_counter()
            sol = c.solve({"x0": x})
            times.append(time.perf_counter() - start)
            iters.append(sol.iterations)
            statuses[sol.status] = statuses.get(sol.status, 0) + 1
            values.append(sol.objective)
    out = {}
    for label, (times, iters, statuses, values) in runs.items():
        per_iter = np.array(times) / np.maximum(np.array(iters), 1)
        out[label] = {"median_s": float(np.median(times)),
                      "max_s": round(float(np.max(times)), 4),
                      "median_iters": float(np.median(iters)),
                      "median_ms_per_iter": round(1e3 * float(np.median(per_iter)), 3),
                      "statuses": ",".join(f"{k}:{v}" for k, v in sorted(statuses.items())),
                      "_values": values}
    return out


def run(quick: bool = False) -> list[dict]:
    warnings.filterwarnings("ignore")
    d = bicycle_design(N=N)
    deltas = 1e-4 * np.arange(N)
    xs = states(6 if quick else 20)
    rows, compiled = [], {}
    for label, norm in (("norm1", 1), ("norm2", 2), ("norminf", np.inf)):
        ocp = pcbf_slack_problem(d.system, d.X, d.U, d.cbf, N, deltas, d.alpha_f, norm)
        compiled[label] = compile(ocp, "exact")
    ocp = textbook_norm2(pcbf_slack_problem(d.system, d.X, d.U, d.cbf, N, deltas, d.alpha_f, 2),
                         d.alpha_f)
    compiled["textbook"] = compile(ocp, "exact")
    results = _time(compiled, xs)
    old = results.pop("textbook")
    base = results["norm1"]["median_s"]
    for label, res in results.items():
        rows.append({"name": f"lane-keeping (2.24) N=50 ipopt {label}",
                     **{k: v for k, v in res.items() if not k.startswith("_")},
                     **({} if label == "norm1" else
                        {"baseline": "norm1", "ratio": base / res["median_s"]})})
    # the old form's values next to the backend's: how many states it got wrong (> 1e-4 rel.)
    wrong = sum(abs(a - b) > 1e-4 * (1 + abs(b))
                for a, b in zip(old["_values"], results["norm2"]["_values"]))
    rows.append({"name": "lane-keeping (2.24) N=50 ipopt norm2 (textbook epigraph)",
                 "median_s": old["median_s"], "baseline": "backend norm2",
                 "ratio": results["norm2"]["median_s"] / old["median_s"],
                 "max_s": old["max_s"], "median_iters": old["median_iters"],
                 "median_ms_per_iter": old["median_ms_per_iter"],
                 "statuses": old["statuses"], "values_differ": int(wrong)})
    return rows
