"""fatrop's CasADi-generated C on the rendezvous (5.15), N = 200 (issue #14, "≤ 10 ms per
step"): a measurement, not part of ``balustrade bench`` (leading underscore).

What it does:

1. builds (5.15) (:func:`~balustrade.problems.robust.robust_pcbf_slack_problem`, thesis
   §6.5 design of :mod:`balustrade.reproduce.rendezvous`) on ``structured-ip-noretry`` (CasADi
   ``fatrop`` on the stage-ordered NLP, :mod:`balustrade.backends.passes.stage_order`), on
   ``fast-convex`` (balustrade's direct Clarabel backend) and as the hand-written Clarabel
   baseline (:mod:`benchmarks._clarabel_direct`);
2. generates fatrop's C for the same NLP and options plus ``error_on_fail`` (the C returns
   nonzero unless fatrop ended with ``Success``, so an acceptable stop is an error here, never
   an optimum), compiles it with ``gcc -O2`` against the casadi wheel's libfatrop/libblasfeo
   and loads it with ``casadi.external``;
3. times one (5.15) solve per path at the states of ``bench_robust`` (a disturbed closed loop
   of the hand-written Algorithm 5.2, seed 0; the first state is a warm-up), interleaved state
   by state, path after path, ``passes`` times; fatrop is started cold (the backend's initial
   guess), as Python's ``structured-ip`` does without a warm start — Clarabel has none;
4. checks the answers: the C's status (``error_on_fail``), its objective against
   ``fast-convex``'s and the baseline's (``|ΔJ| / max(1, |J|)``; also ``fast-convex``
   against the baseline, whose Clarabel keeps its default gap tolerance), its largest
   violation of a row or bound of the solver's NLP, and its primal against Python's fatrop
   (same solver, same start: the same iterations).

Run (~3–6 min under load)::

    PYTHONPATH=$PWD python -m benchmarks._rendezvous_fatrop_c [--passes 2] [--N 200]

This module names fatrop's options because it is benchmark code measuring that solver, not
part of the library.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import time
from pathlib import Path

import casadi as ca
import numpy as np

from balustrade.backends import compile
from balustrade.backends.emittable import INCLUDE_SUBDIRS
from balustrade.problems.multiobjective import multiobjective_pcbf_problem
from balustrade.problems.robust import fuel_objective, robust_pcbf_slack_problem
from balustrade.reproduce.rendezvous import design
from benchmarks import _clarabel_direct as hw
from benchmarks.bench_robust import closed_loop_states

BUILD = Path(os.environ.get("RDV_FATROP_BUILD", "/tmp/rdv_fatrop_c"))


def build_c(c, name: str, opt: str = "-O2", lowering: str = "expanded"
            ) -> tuple[ca.Function, dict]:
    """fatrop's C for the compiled stage-ordered problem ``c``: the same options plus
    ``error_on_fail``, on the solver's own (expanded SX) NLP or, ``lowering="compact"``, on
    the compact lowering in stage order that ``codegen.emit_pcbf`` emits
    (``CasadiCompiled.staged_compact``: same values); returns (the loaded function, build
    facts)."""
    BUILD.mkdir(parents=True, exist_ok=True)
    opts = {**c.options, "error_on_fail": True}
    if lowering == "compact":
        nlp, caches = c.staged_compact()
        solver = ca.nlpsol(name, "fatrop", nlp, {**opts, "cache": caches["fatrop"]})
    else:
        solver = ca.nlpsol(name, "fatrop", c.nlp, {**opts, **c.derivatives})
    cwd = os.getcwd()
    os.chdir(BUILD)
    try:
        t0 = time.perf_counter()
        solver.generate(f"{name}.c", {"with_header": False})
        t_gen = time.perf_counter() - t0
    finally:
        os.chdir(cwd)
    src, lib = BUILD / f"{name}.c", BUILD / f"lib{name}.so"
    cdir = Path(ca.__file__).parent
    inc = [f"-I{cdir / 'include'}"] + [f"-I{cdir / 'include' / s}"
                                       for s in INCLUDE_SUBDIRS["fatrop"]]
    cmd = ["gcc", "-shared", "-fPIC", opt, "-o", str(lib), str(src), *inc, f"-L{cdir}",
           f"-Wl,-rpath,{cdir}", "-lfatrop", "-lblasfeo", "-lm"]
    t0 = time.perf_counter()
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=1200)
    t_build = time.perf_counter() - t0
    if out.returncode != 0:
        raise RuntimeError(out.stderr[-3000:])
    facts = {"source_MB": round(src.stat().st_size / 1e6, 2),
             "source_lines": sum(1 for _ in src.open()),
             "generate_s": round(t_gen, 1), "gcc_s": round(t_build, 1), "flags": opt,
             "lowering": lowering}
    return ca.external(name, str(lib)), facts


def c_solve(f: ca.Function, c, p: np.ndarray) -> tuple[dict | None, float, str]:
    """One call of the generated solver from the backend's cold initial guess."""
    x0, lam_x0, lam_g0 = c._initial_guess(None, p)
    start = time.perf_counter()
    try:
        res = f(x0=x0, p=ca.DM(p), lbx=c.lbx, ubx=c.ubx, lbg=c.lbg, ubg=c.ubg,
                lam_x0=lam_x0, lam_g0=lam_g0)
        msg = "Success"
    except RuntimeError as exc:  # error_on_fail: fatrop did not end with Success
        res, msg = None, str(exc).splitlines()[-1][:120]
    return res, time.perf_counter() - start, msg


def c_objective(c, res: dict, p: np.ndarray) -> tuple[float, float, np.ndarray]:
    """(declared objective, largest violation of a row or bound, layout primal) of a C
    answer, mapped back to the layout's order and projected onto its bounds as
    ``CasadiCompiled._solve_with`` does."""
    w_all = np.asarray(res["x"]).reshape(-1)
    x_orig = np.clip(c.stages.primal(w_all), *c._layout_bounds)
    viol = c._primal_residual(w_all, p)
    return float(c.inverse.objective(x_orig, ca.DM(p))), viol, w_all


def main(N: int = 200, passes: int = 2, n_states: int = 12, lowering: str = "expanded",
         opt: str = "-O2", problem: str = "5.15") -> dict:
    """Times (5.15) or, ``problem="6.15"``, (6.15) with the fuel objective and the bound
    ``h_r(x) + 10⁻²(1 + h_r(x))`` of a ``fast-convex`` (5.15) solve (as ``bench_structured``;
    its running sum of (6.15g) is a lifted stage state, so only ``lowering="expanded"``)."""
    d = design(N, 40)
    data = hw.RendezvousData.from_design(d)
    base = hw.DirectRendezvous(data)
    states = closed_loop_states(d, base, n_states + 1)
    sys_, s, err, cbf = d["system"], d["setup"], d["error"], d["cbf"]
    slack = robust_pcbf_slack_problem(sys_, s.X, s.U, cbf, s.N, s.deltas(), err, s.alpha_f)
    fc515 = compile(slack, "fast-convex")
    if problem == "6.15":
        ocp = multiobjective_pcbf_problem(sys_, s.X, s.U, cbf, s.N, s.deltas(), err,
                                          s.alpha_f, objective=fuel_objective)
        params = []
        for x in states:
            h = fc515.solve({"x0": x}).objective
            params.append({"x0": x, "u_p": np.zeros(3), "bound": h + 1e-2 * (1 + abs(h))})
    else:
        ocp, params = slack, [{"x0": x} for x in states]
    fat, fc = compile(ocp, "structured-ip-noretry"), compile(ocp, "fast-convex")
    tag = problem.replace(".", "")
    f_c, facts = build_c(fat, f"rdv{tag}_N{N}_{lowering}", opt, lowering)
    print("C:", facts, flush=True)
    t = {k: [] for k in ("fatrop C", "fatrop Python", "fast-convex", "hand-written")}
    its = {k: [] for k in t}
    worst = {"obj_rel_vs_fc": 0.0, "obj_rel_vs_hw": 0.0, "fc_vs_hw": 0.0, "viol_C": 0.0,
             "primal_C_vs_python": 0.0}
    failed = dict.fromkeys(t, 0)
    msgs = []
    for _ in range(passes):
        for j, (x, par) in enumerate(zip(states, params, strict=True)):
            p = ocp.pack_parameters(par)
            res, el_c, msg = c_solve(f_c, fat, p)
            sp = fat.solve(par)
            sf = fc.solve(par)
            rh = base.solve_slack(x)[0] if problem == "5.15" else \
                base.solve_mo(x, float(par["bound"]))[0]
            if not j:
                continue
            t["fatrop C"].append(el_c)
            t["fatrop Python"].append(sp.solve_time)
            t["fast-convex"].append(sf.solve_time)
            t["hand-written"].append(rh.solve_time)
            its["fatrop Python"].append(sp.iterations)
            its["fast-convex"].append(sf.iterations)
            its["hand-written"].append(rh.iterations)
            if sp.status != "optimal":
                failed["fatrop Python"] += 1
                msgs.append(f"Python fatrop at state {j}: {sp.status}, {sp.iterations} "
                            f"iterations, {sp.message}")
            failed["fast-convex"] += sf.status != "optimal"
            failed["hand-written"] += not rh.ok
            if sf.status == "optimal" and rh.ok:
                worst["fc_vs_hw"] = max(worst["fc_vs_hw"], abs(sf.objective - rh.objective)
                                        / max(1.0, abs(rh.objective)))
            if res is None:
                failed["fatrop C"] += 1
                msgs.append(f"C at state {j}: {msg}")
                continue
            obj, viol, w_all = c_objective(fat, res, p)
            ref = sf.objective
            worst["obj_rel_vs_fc"] = max(worst["obj_rel_vs_fc"],
                                         abs(obj - ref) / max(1.0, abs(ref)))
            worst["obj_rel_vs_hw"] = max(worst["obj_rel_vs_hw"],
                                         abs(obj - rh.objective) / max(1.0, abs(rh.objective)))
            worst["viol_C"] = max(worst["viol_C"], viol)
            if sp.raw.get("x") is not None:
                worst["primal_C_vs_python"] = max(worst["primal_C_vs_python"], float(
                    np.max(np.abs(w_all - sp.raw["x"]))))
    ref = np.array(t["hand-written"])
    rows = {}
    for k, v in t.items():
        v = np.array(v)
        rows[k] = {"median_ms": round(1e3 * float(np.median(v)), 2),
                   "worst_ms": round(1e3 * float(np.max(v)), 2),
                   "paired_vs_handwritten": round(float(np.median(v / ref)), 3),
                   "iterations_median": float(np.median(its[k])) if its[k] else None,
                   "failed": int(failed[k]), "solves": int(v.size)}
        print(f"{k:14s}", rows[k], flush=True)
    print("agreement:", {k: float(f"{v:.2g}") for k, v in worst.items()}, flush=True)
    if msgs:
        print("failures:", msgs[:8], flush=True)
    return {"rows": rows, "agreement": worst, "build": facts, "failures": msgs}


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--N", type=int, default=200)
    ap.add_argument("--passes", type=int, default=2)
    ap.add_argument("--states", type=int, default=12)
    ap.add_argument("--lowering", choices=("expanded", "compact"), default="expanded")
    ap.add_argument("--opt", default="-O2", help="gcc optimization flag")
    ap.add_argument("--problem", choices=("5.15", "6.15"), default="5.15")
    args = ap.parse_args()
    main(args.N, args.passes, args.states, args.lowering, args.opt, args.problem)
