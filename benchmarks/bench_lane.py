"""Algorithm 6.4 on the lane change (§8.2, ``N = 20``, ``robust-sqp``): the step of the
multiobjective robust PCBF in Python and in its emitted C, with (6.15g) written as one row
(the form before session 10) and in running-sum form (the default on CasADi targets,
:func:`balustrade.problems.multiobjective._running_sum_decrease`).

The four controllers run the seed-0 closed loop of :mod:`balustrade.reproduce.lane_change`
(``x_0 = (0.4, 0, 1.1, 0)``, the destabilizing driver, seeded disturbances), each along its
own trajectory, stepped in turn (A, B, C, D, A, B, …) so the machine's load hits all alike.
Reported per controller: median, 90th percentile and largest step time (wall clock), the
median SQP iterations of the (6.15) solves (Python), and the largest input difference
between the two forms (Python) and between C and Python (same form). ``ratio``: the median
step of the single-row form over the running-sum form, Python and C separately.

Run: ``PYTHONPATH=$PWD python -m balustrade.cli bench --only bench_lane [--quick]``.
"""

from __future__ import annotations

import time

import numpy as np

from balustrade.codegen import accelerate
from balustrade.control.multiobjective import MultiobjectivePCBFController
from balustrade.examples.bicycle import bicycle_design
from balustrade.reproduce import lane_change as L

FORMS = {"single row": False, "running sum": True}


def _controllers(d: object) -> dict[str, object]:
    common = (d.system, d.X, d.U, d.cbf, d.pi_f, d.N, d.deltas, d.error, d.alpha_f)
    out = {}
    for label, running in FORMS.items():
        py = MultiobjectivePCBFController.build(*common, rho=L.RHO, target=L.TARGET,
                                                slack_target=L.TARGET, running_sum=running)
        out[f"Python, {label}"] = py
        out[f"C, {label}"] = accelerate(py)
    return out


def run(quick: bool = False) -> list[dict]:
    d = bicycle_design(N=20)
    ctrls = _controllers(d)
    steps = 40 if quick else L.STEPS
    ws = L.disturbances(d, 0, steps)
    xs = {k: L.X0.copy() for k in ctrls}
    times: dict[str, list[float]] = {k: [] for k in ctrls}
    inputs: dict[str, list[np.ndarray]] = {k: [] for k in ctrls}
    iters: dict[str, list[int]] = {k: [] for k in ctrls}
    not_ok = dict.fromkeys(ctrls, 0)
    for c in ctrls.values():
        c.reset()
    for w in ws:
        for k, c in ctrls.items():
            x = xs[k]
            start = time.perf_counter()
            u, info = c.step(x, L.human(x))
            times[k].append(time.perf_counter() - start)
            inputs[k].append(np.asarray(u, dtype=float))
            not_ok[k] += info.status != "ok"
            sol = info.solutions.get("problem")
            if sol is not None and getattr(sol, "iterations", None) is not None:
                iters[k].append(int(sol.iterations))
            xs[k] = d.system.step(x, u, w)
    rows = []
    for k in ctrls:
        t = np.asarray(times[k])
        row = {"name": f"lane change, Algorithm 6.4 step, {k}",
               "median_s": float(np.median(t)), "p90_s": float(np.percentile(t, 90)),
               "max_s": float(t.max()), "steps": int(t.size), "not_ok": int(not_ok[k])}
        if iters[k]:
            row["median_sqp_iterations"] = float(np.median(iters[k]))
        rows.append(row)
    diff = {lang: float(np.max(np.abs(np.array(inputs[f"{lang}, single row"])
                                      - np.array(inputs[f"{lang}, running sum"]))))
            for lang in ("Python", "C")}
    for row in rows:
        lang, form = row["name"].rsplit(", ", 2)[-2:]
        other = "running sum" if form == "single row" else "single row"
        if form == "running sum":
            base = next(r for r in rows if r["name"].endswith(f"{lang}, {other}"))
            row["baseline"] = f"{lang}, {other}"
            row["ratio"] = base["median_s"] / row["median_s"]
            row["max_input_diff_vs_single_row"] = diff[lang]
        if lang == "C":
            row["max_input_diff_vs_python"] = float(np.max(np.abs(
                np.array(inputs[f"C, {form}"]) - np.array(inputs[f"Python, {form}"]))))
    return rows


if __name__ == "__main__":
    for r in run(quick=True):
        print(r)
