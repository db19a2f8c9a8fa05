"""IPOPT time per solve of the slack problem (2.24) with the slack norms 1, 2 and ∞ on a
nonlinear lane-keeping PCBF: the kinematic bicycle of Section 8.2 (4 states, 2 inputs),
``N = 50``, the lane box ``X``, terminal CBF around ``x_s = (0, 0, 1.1, 0)``, ``α_f = 10⁶``,
``Δ_i = 10⁻⁴ i``, from 20 seeded states inside and outside the lane (issue #12).

``norm2 (textbook epigraph)`` is the same problem with ``‖ξ_i‖₂`` written as
``ξ_iᵀξ_i − t_i² <= 0``, ``t_i >= 0`` by hand — the lowering the CasADi backend used before
issue #12 (degenerate at ``ξ_i = 0``); ``ratio`` is its median over the backend's. ``quick``
uses 6 states.
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


def _time(compiled, xs: list[np.ndarray]) -> dict:
    times, iters, statuses, values = [], [], {}, []
    for x in xs:
        start = time.perf_counter()
        sol = compiled.solve({"x0": x})
        times.append(time.perf_counter() - start)
        iters.append(sol.iterations)
        statuses[sol.status] = statuses.get(sol.status, 0) + 1
        values.append(sol.objective)
    return {"median_s": float(np.median(times)), "max_s": round(float(np.max(times)), 4),
            "median_iters": float(np.median(iters)),
            "statuses": ",".join(f"{k}:{v}" for k, v in sorted(statuses.items())),
            "_values": values}


def run(quick: bool = False) -> list[dict]:
    warnings.filterwarnings("ignore")
    d = bicycle_design(N=N)
    deltas = 1e-4 * np.arange(N)
    xs = states(6 if quick else 20)
    rows, results = [], {}
    for label, norm in (("norm1", 1), ("norm2", 2), ("norminf", np.inf)):
        ocp = pcbf_slack_problem(d.system, d.X, d.U, d.cbf, N, deltas, d.alpha_f, norm)
        results[label] = _time(compile(ocp, "exact"), xs)
    ocp = textbook_norm2(pcbf_slack_problem(d.system, d.X, d.U, d.cbf, N, deltas, d.alpha_f, 2),
                         d.alpha_f)
    old = _time(compile(ocp, "exact"), xs)
    for label, res in results.items():
        rows.append({"name": f"lane-keeping (2.24) N=50 ipopt {label}",
                     **{k: v for k, v in res.items() if not k.startswith("_")}})
    # the old form's values next to the backend's: how many states it got wrong (> 1e-4 rel.)
    wrong = sum(abs(a - b) > 1e-4 * (1 + abs(b))
                for a, b in zip(old["_values"], results["norm2"]["_values"]))
    rows.append({"name": "lane-keeping (2.24) N=50 ipopt norm2 (textbook epigraph)",
                 "median_s": old["median_s"], "baseline": "backend norm2",
                 "ratio": old["median_s"] / results["norm2"]["median_s"],
                 "max_s": old["max_s"], "median_iters": old["median_iters"],
                 "statuses": old["statuses"], "values_differ": int(wrong)})
    return rows
