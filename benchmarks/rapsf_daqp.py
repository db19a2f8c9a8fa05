"""DAQP through its own interface, hot-started, against PIQP on the QPs (4.5) of Algorithm 4.1
(thesis Chapter 4, SPEC §2.21; docs/adaptive.md, "Session 14: DAQP's own interface")::

    PYTHONPATH=$PWD python -m benchmarks.rapsf_daqp [masses] [steps] [options]
    PYTHONPATH=$PWD python -m benchmarks.rapsf_daqp loop [masses] [steps]

The closed loop of :mod:`benchmarks.rapsf_split` (design of ``reproduce msd-adaptive``, box
update, ``fast-convex``; the loop applies PIQP's answers) runs as usual. 3 masses: every solve
of (4.5) by the direct backend's PIQP engine is also handed to a
:class:`~balustrade.backends.daqp_engine.DaqpEngine` on the same lowered data (``q``, ``b``,
the values of ``A(p)``), kept across the loop (hot from the previous working set). 8 masses
(``fast-convex`` becomes row generation, ``RAPSF``): every *reduced* QP that PIQP solves is
also handed to DAQP — the same engine for the reduced QP's rows, updated while a round's rows
are the last round's, else set up anew with the last DAQP point as primal start (the warm
start DAQP's set-up offers; ``eq_reduction`` on: it eliminated the 336 equality rows and cut
the solves several-fold in a trial). The two solvers take turns in going first.

Per solve: wall and CPU time (``time.process_time``) of each, DAQP's exit flag and iterations,
the KKT residual of DAQP's answer on the lowered QP, whether the engine accepted it (flag
optimal *and* residual <= 1e-8) or fell back to PIQP, ``|v_0|`` and objective differences.
``options``: DAQP settings of the engine as a Python dict literal (e.g.
``"{'primal_tol': 1e-6, 'eta_prox': -1.0}"``, DAQP's own defaults) over the engine's.
``loop``: :func:`loops`, two closed loops (``fast-convex`` and ``fast-convex-daqp``) taking
turns every step, step times and input differences.
"""

from __future__ import annotations

import ast
import sys
import time
from types import SimpleNamespace

import numpy as np
import scipy.sparse as sp

from balustrade.backends import row_generation as rg
from balustrade.backends.daqp_engine import DaqpEngine
from balustrade.control.rapsf import RAPSF
from balustrade.reproduce import msd_adaptive
from benchmarks.bench_rapsf import Loop


class Timed:
    """A :class:`DaqpEngine` whose :meth:`run` also records the time of DAQP alone (update
    and solve, without the KKT check), its flag and KKT residual: the DAQP calls are timed
    by wrapping the model's ``update``/``solve``/``setup``."""

    def __init__(self, engine: DaqpEngine):
        self.engine = engine
        self.daqp_s = self.daqp_cpu = 0.0
        self.flag: int | None = None
        self.kkt = float("nan")
        self.z: np.ndarray | None = None

    def run(self, q, b, A=None):
        eng = self.engine
        self.daqp_s = self.daqp_cpu = 0.0
        self.flag = None
        orig_setup = eng._setup

        def setup(q_, b_):
            c0, t0 = time.process_time(), time.perf_counter()
            flag = orig_setup(q_, b_)
            self.daqp_s += time.perf_counter() - t0
            self.daqp_cpu += time.process_time() - c0
            if eng.model is not None:
                self._wrap(eng.model)
            return flag
        eng._setup = setup
        if eng.model is not None:
            self._wrap(eng.model)
        before, fresh = eng.fallbacks, eng.model is None
        c0, t0 = time.process_time(), time.perf_counter()
        raw = eng.run(q, b, A)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        eng._setup = orig_setup
        self.flag, self.kkt = eng.last
        return raw, {"wall": wall, "cpu": cpu, "daqp_s": self.daqp_s,
                     "daqp_cpu": self.daqp_cpu, "flag": self.flag, "kkt": self.kkt,
                     "fallback": eng.fallbacks > before, "setup": fresh}

    def _wrap(self, model) -> None:
        if getattr(model, "_timed", False):
            return
        outer = self

        class Proxy:
            _timed = True

            def __init__(self, m):
                self.m = m

            def update(self, **kw):
                c0, t0 = time.process_time(), time.perf_counter()
                out = self.m.update(**kw)
                outer.daqp_s += time.perf_counter() - t0
                outer.daqp_cpu += time.process_time() - c0
                return out

            def solve(self):
                c0, t0 = time.process_time(), time.perf_counter()
                out = self.m.solve()
                outer.daqp_s += time.perf_counter() - t0
                outer.daqp_cpu += time.process_time() - c0
                return out

        self.engine.model = Proxy(model)


def _stats(raw_piqp, t_piqp, c_piqp, raw_d, info, P, q, idx) -> dict:
    yp, yd = raw_piqp.y, raw_d.y
    row = {"piqp_s": t_piqp, "piqp_cpu": c_piqp, "piqp_iter": raw_piqp.iterations,
           "piqp_status": raw_piqp.status.value, "daqp_iter": raw_d.iterations,
           "status": raw_d.status.value, **info}
    if yp is not None and yd is not None:
        row["dv0"] = float(np.max(np.abs(yp[idx] - yd[idx])))
        row["dobj"] = float(abs((0.5 * yp @ (P @ yp) + q @ yp) - (0.5 * yd @ (P @ yd) + q @ yd)))
    return row


def compare(masses: int, steps: int, options: dict | None = None) -> dict:
    """The closed loop with every (4.5) solve (3 masses) or every reduced QP of the row
    generation (8 masses) also solved by DAQP, taking turns in going first."""
    d = msd_adaptive.design(masses)
    ctrl = msd_adaptive.adaptive_controller(d, target="fast-convex")
    loop = Loop(d, ctrl.step, steps)
    rows: list[dict] = []
    wrapped: set[int] = set()

    def v_index(compiled) -> np.ndarray:
        n_w = compiled.program.n_w
        return np.asarray(compiled.ocp.unpack_variables(np.arange(n_w, dtype=float))["v"]
                          )[:, 0].astype(int)

    def wrap_engine(compiled) -> None:
        engine, prog = compiled.engine, compiled.program
        run = engine.run
        timed = Timed(DaqpEngine(prog, dict(options or {})))
        idx = v_index(compiled)

        last_A: list = [None]

        def both(q, b, A=None):
            changed = A is not None and last_A[0] is not None \
                and not np.array_equal(A, last_A[0])
            last_A[0] = None if A is None else A.copy()
            daqp_first = len(rows) % 2 == 1
            if daqp_first:
                raw_d, info = timed.run(q, b, A)
            c0, t0 = time.process_time(), time.perf_counter()
            raw = run(q, b) if A is None else run(q, b, A)
            t_p, c_p = time.perf_counter() - t0, time.process_time() - c0
            if not daqp_first:
                raw_d, info = timed.run(q, b, A)
            rows.append(_stats(raw, t_p, c_p, raw_d, info, timed.engine.P, q, idx))
            rows[-1]["A_changed"] = changed
            return raw
        engine.run = both

    state: dict = {"timed": None, "rows_of": None}
    orig = rg.RowGeneration._solve_reduced

    def reduced(self, q, A_eq, b_eq, G, h, solver=None):
        if "idx" not in state:             # the first step (compiles): not compared
            return orig(self, q, A_eq, b_eq, G, h, solver)
        G = sp.csc_matrix(G)
        key = self._red[0] if self._red is not None else None
        if state["timed"] is None or state["rows_of"] is None or key is None \
                or not np.array_equal(state["rows_of"], key):
            A = sp.vstack([A_eq, G]).tocsc()
            A.sort_indices()
            prog = SimpleNamespace(conic=False, P=self._P, A=A, n_y=A.shape[1],
                                   cones=[("zero", A_eq.shape[0]), ("nonneg", G.shape[0])],
                                   b0=np.concatenate([b_eq, h]), q0=q)
            last = state["timed"]
            engine = DaqpEngine(prog, {"eq_reduction": 1, **(options or {})})
            if last is not None and last.engine.model is not None:
                engine._start = last.last_x
            state["timed"] = Timed(engine)
            state["timed"].pattern = A
            state["rows_of"] = None if key is None else key.copy()
        timed = state["timed"]
        A_now = sp.vstack([A_eq, G]).tocsc()
        A_now.sort_indices()
        b = np.concatenate([b_eq, h])
        daqp_first = len(rows) % 2 == 1
        if daqp_first:
            raw_d, info = timed.run(q, b, A_now.data)
        c0, t0 = time.process_time(), time.perf_counter()
        raw, solver = orig(self, q, A_eq, b_eq, G, h, solver)
        t_p, c_p = time.perf_counter() - t0, time.process_time() - c0
        if not daqp_first:
            raw_d, info = timed.run(q, b, A_now.data)
        timed.last_x = raw_d.y.copy() if raw_d.y is not None else None
        rows.append(_stats(raw, t_p, c_p, raw_d, info, timed.engine.P, q, state["idx"]))
        rows[-1]["m"] = b.size
        return raw, solver

    if masses > 3:
        rg.RowGeneration._solve_reduced = reduced
    try:
        for k in range(steps):
            for compiled in ctrl._compiled.values():
                if id(compiled) not in wrapped:
                    wrapped.add(id(compiled))
                    if compiled.rowgen is None:
                        wrap_engine(compiled)
                    else:
                        state["idx"] = v_index(compiled)
            loop(k)
    finally:
        rg.RowGeneration._solve_reduced = orig
    return {"masses": masses, "steps": steps, "rows": rows, "fallbacks": loop.fallbacks}


def summary(r: dict, skip: int = 1) -> str:
    """Per-solve medians/90th percentiles/worst after the first ``skip`` solves (DAQP's
    cold set-up), statuses, agreement."""
    rows = r["rows"][skip:]
    if not rows:
        return "no solves"

    def col(k):
        return np.array([x.get(k, np.nan) for x in rows], dtype=float)

    def q3(v):
        return (f"median {1e3 * np.median(v):7.3f}  p90 {1e3 * np.percentile(v, 90):7.3f}  "
                f"worst {1e3 * v.max():8.3f} ms")
    first = r["rows"][0]
    flags: dict = {}
    for x in rows:
        flags[x["flag"]] = flags.get(x["flag"], 0) + 1
    kkt = col("kkt")
    ratio = col("piqp_s") / col("wall")
    lines = [
        f"{r['masses']} masses, {len(rows)} solves after {skip} cold (cold DAQP "
        f"{1e3 * first['wall']:.2f} ms, flag {first['flag']}; PIQP "
        f"{1e3 * first['piqp_s']:.2f} ms); loop fallbacks {r['fallbacks']}",
        f"  PIQP          wall {q3(col('piqp_s'))}\n                CPU  "
        f"{q3(col('piqp_cpu'))}; iterations median "
        f"{np.median(col('piqp_iter')):.0f}, max {col('piqp_iter').max():.0f}",
        f"  DAQP engine   wall {q3(col('wall'))}\n                CPU  "
        f"{q3(col('cpu'))} (incl. KKT check, fallbacks)",
        f"  DAQP alone    wall {q3(col('daqp_s'))}\n                CPU  "
        f"{q3(col('daqp_cpu'))}; iterations median "
        f"{np.median(col('daqp_iter')):.0f}, max {col('daqp_iter').max():.0f}",
        f"  per-solve ratio PIQP / DAQP engine: median {np.median(ratio):.2f}, "
        f"10th percentile {np.percentile(ratio, 10):.2f}",
        f"  DAQP flags {flags}; KKT residual (flag 1) max {np.nanmax(kkt):.1e}, > 1e-8 on "
        f"{int(np.sum(kkt > 1e-8))}; fallbacks to PIQP {int(sum(x['fallback'] for x in rows))}"
        f"; engine statuses {sorted({x['status'] for x in rows})}; PIQP statuses "
        f"{sorted({x['piqp_status'] for x in rows})}",
        f"  max |v_0 difference| {np.nanmax(col('dv0')):.1e}, max |objective difference| "
        f"{np.nanmax(col('dobj')):.1e}",
    ]
    if "m" in rows[0]:
        lines.append(f"  reduced QP rows {int(col('m').min())}-{int(col('m').max())}")
    if "A_changed" in rows[0]:
        changed = col("A_changed").astype(bool)
        for label, pick in (("with a changed A(p) (new Θ_k)", changed), ("same A(p)", ~changed)):
            if pick.any():
                lines.append(f"  solves {label}: {int(pick.sum())}, DAQP iterations median "
                             f"{np.median(col('daqp_iter')[pick]):.1f}, engine CPU median "
                             f"{1e3 * np.median(col('cpu')[pick]):.3f} ms")
    setup = col("setup").astype(bool)
    for label, pick in (("set up anew", setup), ("updated (kept model)", ~setup)):
        if pick.any():
            lines.append(f"  DAQP {label}: {int(pick.sum())} solves, engine CPU median "
                         f"{1e3 * np.median(col('cpu')[pick]):.3f} ms against PIQP's "
                         f"{1e3 * np.median(col('piqp_cpu')[pick]):.3f} ms on the same QPs")
    return "\n".join(lines)


def loops(masses: int, steps: int) -> dict:
    """Two closed loops, ``fast-convex`` (the default) and ``fast-convex-daqp``, same ``θ*``
    and disturbances, taking turns every step (which goes first alternates). Step times
    (the first, compiling step not timed), inputs' largest difference, fallbacks."""
    d = msd_adaptive.design(masses)
    s = d["setup"]

    def controller(target: str) -> RAPSF:      # msd_adaptive.adaptive_controller's, retargeted
        return RAPSF(d["system"], d["X0"], msd_adaptive.joint(d), None, s.W, d["K"], s.N,
                     s.Theta0, estimator=msd_adaptive.BoxUpdate(d["system"], s.W, s.Theta0),
                     target=target)
    ctrls = {"fast-convex": msd_adaptive.adaptive_controller(d, target="fast-convex"),
             "fast-convex-daqp": controller("fast-convex-daqp")}
    runs = {k: Loop(d, c.step, steps) for k, c in ctrls.items()}
    for loop in runs.values():
        loop(0)
    for k in range(1, steps):
        for label in (list(runs) if k % 2 else list(runs)[::-1]):
            runs[label](k)
    t = {k: np.array(v.times[1:]) for k, v in runs.items()}
    du = float(np.max(np.abs(np.array(runs["fast-convex"].applied)
                             - np.array(runs["fast-convex-daqp"].applied))))
    engines = [c.engine for c in ctrls["fast-convex-daqp"]._compiled.values()]
    return {"times": t, "max_du": du, "fallbacks": {k: v.fallbacks for k, v in runs.items()},
            "engine_fallbacks": sum(getattr(e, "fallbacks", 0) for e in engines),
            "verified": sum(getattr(e, "verified", 0) for e in engines)}


def main(argv: list[str]) -> None:
    if argv and argv[0] == "loop":
        masses = int(argv[1]) if len(argv) > 1 else 3
        steps = int(argv[2]) if len(argv) > 2 else 150
        r = loops(masses, steps)
        print(f"{masses} masses, two closed loops of {steps} steps taking turns (first step "
              "not timed)")
        for k, v in r["times"].items():
            print(f"  {k:<17} step median {1e3 * np.median(v):7.3f}  p90 "
                  f"{1e3 * np.percentile(v, 90):7.3f}  worst {1e3 * v.max():8.3f} ms; "
                  f"loop fallbacks {r['fallbacks'][k]}")
        ratio = r["times"]["fast-convex"] / r["times"]["fast-convex-daqp"]
        print(f"  per-step ratio fast-convex / fast-convex-daqp: median {np.median(ratio):.2f}"
              f"; max |u difference| {r['max_du']:.1e}; DAQP answers verified "
              f"{r['verified']}, fallbacks to PIQP {r['engine_fallbacks']}")
        return
    masses = int(argv[0]) if argv else 3
    steps = int(argv[1]) if len(argv) > 1 else 150
    options = ast.literal_eval(argv[2]) if len(argv) > 2 else None
    print(summary(compare(masses, steps, options)))


if __name__ == "__main__":
    main(sys.argv[1:])
