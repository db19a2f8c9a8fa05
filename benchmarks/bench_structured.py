"""Structure-exploiting CasADi solvers against IPOPT and the dense SQP (issue #14 §2, #12).

Problems (each solved cold from the same seeded states; times per solve, interleaved: for
every state all targets in turn, so load drifts hit every target alike):

* rendezvous (5.15) and (6.15), ``N = 200`` (thesis §6.5; (6.15) with the fuel objective,
  ``u_p`` seeded in ``U`` and the decrease bound ``h_r(x) + 10⁻²(1 + h_r(x))`` from an exact
  (5.15) solve, so every state is feasible);
* the nonlinear bicycle (5.15), ``N = 20`` (Section 8.2 design);
* the nonlinear lane-keeping slack problem (2.24), ``N = 50``, slack norms 1, 2, ∞ (the
  problem of ``bench_norms.py``);
* the cart-pole PCBF pair (2.24) + (2.23), ``N = 20``, RK4 (:mod:`balustrade.examples.cartpole`):
  (2.24) on seeded states of ``X``, (2.23) with the proposal of the closed-loop scenario and
  the slacks of an exact (2.24) solve at the same state.

``structured-ip`` refuses the 2-norm slack cost (a fatrop solve there never returned:
:func:`balustrade.backends.casadi_backend._refuse_fatrop_hang`); that row says so.

Targets: ``exact``, ``long-horizon`` (IPOPT), ``fast-sqp`` (sqpmethod + dense qrqp),
``structured-ip`` (fatrop), ``structured-sqp`` (sqpmethod + HPIPM), the last two on the
stage-ordered NLP (:mod:`balustrade.backends.passes.stage_order`). ``failed`` counts solves
that did not end optimal; ``off`` counts optimal solves whose objective differs from
``exact``'s (also optimal) by more than ``10⁻⁴(1 + |J|)``. A target whose first solve of a
problem takes more than :data:`SLOW_S` seconds is skipped for the rest of that problem.
``quick`` uses 3 states per problem (else 8).
"""

from __future__ import annotations

import sys
import time
import warnings

import numpy as np

from balustrade.backends import compile
from balustrade.backends.passes.stage_order import StructureError
from balustrade.examples.bicycle import bicycle_design
from balustrade.examples.cartpole import cartpole_design, destabilizing_proposal
from balustrade.models.bicycle import DEG
from balustrade.problems.multiobjective import multiobjective_pcbf_problem
from balustrade.problems.pcbf import pcbf_filter_problem, pcbf_slack_problem
from balustrade.problems.robust import fuel_objective, robust_pcbf_slack_problem
from balustrade.reproduce.rendezvous import design as rendezvous_design

TARGETS = ("exact", "long-horizon", "fast-sqp", "structured-ip", "structured-sqp")
#: a target whose first solve takes longer than this is skipped for the problem
SLOW_S = 30.0


def _rendezvous_cases(n: int, rng: np.random.Generator) -> list[tuple]:
    d = rendezvous_design(200, 400)
    sys, s, err, cbf = d["system"], d["setup"], d["error"], d["cbf"]
    slack = robust_pcbf_slack_problem(sys, s.X, s.U, cbf, s.N, s.deltas(), err, s.alpha_f)
    xs = [np.concatenate([rng.uniform(-9, 9, 3), rng.uniform(-4, 4, 3)]) for _ in range(n)]
    exact = compile(slack, "exact")
    h = [exact.solve({"x0": x}).objective for x in xs]
    mo = multiobjective_pcbf_problem(sys, s.X, s.U, cbf, s.N, s.deltas(), err, s.alpha_f,
                                     objective=fuel_objective)
    mo_params = [{"x0": x, "u_p": rng.uniform(-20, 20, 3),
                  "bound": hx + 1e-2 * (1 + abs(hx))} for x, hx in zip(xs, h)]
    return [("rendezvous (5.15) N=200", slack, [{"x0": x} for x in xs]),
            ("rendezvous (6.15) N=200", mo, mo_params)]


def _bicycle_states(n: int, rng: np.random.Generator) -> list[dict]:
    return [{"x0": np.array([rng.uniform(-0.3, 0.3), rng.uniform(-40, 40) * DEG,
                             rng.uniform(0.6, 1.3), rng.uniform(-30, 30) * DEG])}
            for _ in range(n)]


def _bicycle_cases(n: int, rng: np.random.Generator) -> list[tuple]:
    d = bicycle_design(N=20)
    slack = robust_pcbf_slack_problem(d.system, d.X, d.U, d.cbf, d.N, d.deltas, d.error,
                                      d.alpha_f)
    cases = [("bicycle (5.15) N=20", slack, _bicycle_states(n, rng))]
    lane = bicycle_design(N=50)
    deltas = 1e-4 * np.arange(50)
    for label, norm in (("1", 1), ("2", 2), ("inf", np.inf)):
        ocp = pcbf_slack_problem(lane.system, lane.X, lane.U, lane.cbf, 50, deltas,
                                 lane.alpha_f, norm)
        cases.append((f"lane-keeping (2.24) N=50 norm {label}", ocp,
                      _bicycle_states(n, np.random.default_rng(1))))
    return cases


def _cartpole_cases(n: int, rng: np.random.Generator) -> list[tuple]:
    d = cartpole_design()
    args = (d.system, d.X, d.U, d.h_f, d.N, d.deltas)
    slack = pcbf_slack_problem(*args, alpha_f=d.alpha_f, slack_norm=1)
    xs = [np.array([rng.uniform(-0.8, 0.8), rng.uniform(-0.3, 0.3), rng.uniform(-1.5, 1.5),
                    rng.uniform(-2, 2)]) for _ in range(n)]
    exact = compile(slack, "exact")
    filt_params = []
    for k, x in enumerate(xs):
        s = exact.solve({"x0": x})
        filt_params.append({"x0": x, "u_p": destabilizing_proposal(x, k), "xi": s.primal["xi"],
                            "xi_N": s.primal["xi_N"]})
    return [("cart-pole (2.24) N=20", slack, [{"x0": x} for x in xs]),
            ("cart-pole (2.23) N=20", pcbf_filter_problem(*args), filt_params)]


def _measure(name: str, ocp: object, params: list[dict], targets: tuple = TARGETS
             ) -> list[dict]:
    compiled, rows = {}, []
    for tgt in targets:
        try:
            compiled[tgt] = compile(ocp, tgt)
        except StructureError as exc:
            rows.append({"name": name, "target": tgt, "refused": str(exc)[:80]})
    times = {t: [] for t in compiled}
    failed, off, skipped = dict.fromkeys(compiled, 0), dict.fromkeys(compiled, 0), set()
    for par in params:
        ref = None
        for tgt, c in compiled.items():
            if tgt in skipped:
                continue
            start = time.perf_counter()
            sol = c.solve(par)
            elapsed = time.perf_counter() - start
            times[tgt].append(elapsed)
            if elapsed > SLOW_S and len(times[tgt]) == 1:
                skipped.add(tgt)
            if sol.status != "optimal":
                failed[tgt] += 1
            elif tgt == "exact":
                ref = sol.objective
            elif ref is not None and abs(sol.objective - ref) > 1e-4 * (1 + abs(ref)):
                off[tgt] += 1
    base = float(np.median(times["exact"])) if times.get("exact") else np.nan
    for tgt in compiled:
        t = times[tgt]
        rows.append({"name": name, "target": tgt, "median_ms": 1e3 * float(np.median(t)),
                     "max_ms": 1e3 * float(np.max(t)), "vs_exact": float(np.median(t)) / base,
                     "solves": len(t), "failed": failed[tgt], "off": off[tgt],
                     **({"skipped": f"first solve > {SLOW_S:g} s"} if tgt in skipped else {})})
    return rows


def run(quick: bool = False, progress: bool = False, part: str | None = None,
        targets: tuple = TARGETS) -> list[dict]:
    """``part``: ``"nonlinear"`` (bicycle, lane-keeping, cart-pole), ``"cartpole"``,
    ``"rendezvous"`` or ``None`` (all); ``targets`` must start with ``"exact"`` (the
    reference of ``off`` and ``× exact``)."""
    warnings.filterwarnings("ignore")
    n = 3 if quick else 8
    rng = np.random.default_rng(0)
    cases = []
    if part in (None, "nonlinear"):
        cases += _bicycle_cases(n, rng)
    if part in (None, "nonlinear", "cartpole"):
        cases += _cartpole_cases(n, np.random.default_rng(2))
    if part in (None, "rendezvous"):
        cases += _rendezvous_cases(n, rng)
    rows = []
    for name, ocp, params in cases:
        rows += _measure(name, ocp, params, targets)
        if progress:
            print(markdown(rows), file=sys.stderr, flush=True)
    return rows


def markdown(rows: list[dict]) -> str:
    """The rows as the table of ``docs/engines.md``."""
    out = ["| problem | target | median ms | max ms | × exact | failed | off |",
           "|---|---|---:|---:|---:|---:|---:|"]
    for r in rows:
        if "refused" in r:
            out.append(f"| {r['name']} | {r['target']} | refused: {r['refused']} | | | | |")
            continue
        note = " (skipped: slow)" if "skipped" in r else ""
        out.append(f"| {r['name']} | {r['target']}{note} | {r['median_ms']:.1f} | "
                   f"{r['max_ms']:.1f} | {r['vs_exact']:.2f} | {r['failed']}/{r['solves']} | "
                   f"{r['off']} |")
    return "\n".join(out)


if __name__ == "__main__":  # pragma: no cover
    parts = [a for a in sys.argv[1:] if a in ("nonlinear", "cartpole", "rendezvous")]
    chosen = tuple(a.split("=", 1)[1].split(",") for a in sys.argv[1:]
                   if a.startswith("--targets="))
    print(markdown(run(quick="--quick" in sys.argv, progress=True,
                       part=parts[0] if parts else None,
                       targets=chosen[0] if chosen else TARGETS)))
