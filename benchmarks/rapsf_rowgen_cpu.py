"""The 8-mass step of Algorithm 4.1 (thesis Chapter 4, SPEC §2.21) on RAPSF's default (row
generation of (4.5) on PIQP), by CPU time (``time.process_time``) beside wall time, for a
loaded machine (docs/adaptive.md, "Session 15")::

    PYTHONPATH=$PWD python -m benchmarks.rapsf_rowgen_cpu split [masses] [steps]
    PYTHONPATH=$PWD python -m benchmarks.rapsf_rowgen_cpu ab [masses] [steps] [options]
    PYTHONPATH=$PWD python -m benchmarks.rapsf_rowgen_cpu round2 [masses] [steps] [pairs]

``split``: one closed loop (:class:`benchmarks.bench_rapsf.Loop`, the design of ``reproduce
msd-adaptive``) with the controller's parts wrapped by CPU timers (instance attributes and the
``piqp`` module's solver class only); medians per part over the timed steps (the first, which
compiles, is not timed), the rounds per step, the iterations per reduced solve.

``ab``: two closed loops with the same ``θ*`` and disturbances taking turns every step (which
goes first alternates): the default, and the default with the reduced solves' PIQP settings
updated by ``options`` (a Python dict literal, e.g. ``"{'preconditioner_iter': 0}"``; a key
starting with ``@`` sets that attribute of the row generation instead, e.g.
``"{'@seed': 'active'}"``);
median wall and CPU per step, the median per-step CPU ratio, the largest input difference.

``round2``: the reduced QPs of the loop's second rounds (the first round's rows plus the
violated ones, same data) solved by DAQP set up cold, started at the first round's point,
with the first round's active rows marked active (DAQP's ``sense``), against PIQP's solve
of the same QP (set-up and solve, CPU), the first ``pairs`` of them.
"""

from __future__ import annotations

import ast
import os
import sys
import time

import numpy as np
import scipy.sparse as sp

from balustrade.reproduce import msd_adaptive
from benchmarks.bench_rapsf import Loop

V0 = "v"   # the variable whose first column is the applied input (after K x)


def _cpu(fn, acc: dict, part: str):
    """``fn`` adding its CPU time to ``acc[part]`` on every call."""
    def call(*a, **kw):
        c0 = time.process_time()
        try:
            return fn(*a, **kw)
        finally:
            acc[part] = acc.get(part, 0.0) + time.process_time() - c0
    return call


def _rowgen(ctrl) -> object:
    gens = [c.rowgen for c in ctrl._compiled.values() if getattr(c, "rowgen", None)]
    return gens[0] if gens else None


def split(masses: int, steps: int) -> dict:
    """CPU medians per part of the default controller's step (see the module docstring)."""
    import piqp

    import balustrade.estimate.updates as updates
    acc: dict[str, float] = {}
    iters: list[int] = []
    original, lps = piqp.SparseSolver, updates.solve_lps_joint

    class Timed(original):
        def setup(self, *a, **kw):
            return _cpu(super().setup, acc, "PIQP set-up (new rows)")(*a, **kw)

        def update(self, *a, **kw):
            return _cpu(super().update, acc, "PIQP update (same rows)")(*a, **kw)

        def solve(self):
            out = _cpu(super().solve, acc, "PIQP solves")()
            iters.append(int(self.result.info.iter))
            return out

    piqp.SparseSolver = Timed
    updates.solve_lps_joint = _cpu(lps, acc, "estimator LPs")
    try:
        d = msd_adaptive.design(masses)
        ctrl = msd_adaptive.adaptive_controller(d)
        loop = Loop(d, ctrl.step, steps)
        loop(0)
        ctrl.estimator.update = _cpu(ctrl.estimator.update, acc, "estimator")
        ctrl._update_theta = _cpu(ctrl._update_theta, acc, "theta update")
        ctrl._set_theta = _cpu(ctrl._set_theta, acc, "s_jr of a new Θ_k")
        for c in ctrl._compiled.values():
            c.solve = _cpu(c.solve, acc, "backend solve")
            prog = c.program
            prog.q, prog.b = _cpu(prog.q, acc, "q, b, A(p)"), _cpu(prog.b, acc, "q, b, A(p)")
            prog.A_data = _cpu(prog.A_data, acc, "q, b, A(p)")
            if c.rowgen is not None:
                g = c.rowgen
                g.run = _cpu(g.run, acc, "row generation")
                g._rows_at = _cpu(g._rows_at, acc, "all-row check")
                g._reduced = _cpu(g._reduced, acc, "G[rows]")
        gen = _rowgen(ctrl)
        per: dict[str, list[float]] = {}
        rounds = []
        iters.clear()
        for k in range(1, steps):
            acc.clear()
            c0 = time.process_time()
            loop(k)
            acc["step (CPU)"] = time.process_time() - c0
            acc["step (wall)"] = loop.times[-1]
            g = acc.get
            acc["estimator, rest"] = g("estimator", 0.0) - g("estimator LPs", 0.0)
            acc["nesting check"] = g("theta update", 0.0) - g("estimator", 0.0) \
                - g("s_jr of a new Θ_k", 0.0)
            acc["row generation, rest"] = g("row generation", 0.0) - sum(
                g(p, 0.0) for p in ("PIQP set-up (new rows)", "PIQP update (same rows)",
                                    "PIQP solves", "all-row check", "G[rows]"))
            acc["backend, rest"] = g("backend solve", 0.0) - g("row generation", 0.0) \
                - g("q, b, A(p)", 0.0)
            acc["step, rest"] = acc["step (CPU)"] - g("theta update", 0.0) \
                - g("backend solve", 0.0)
            rounds.append(gen.stats.rounds if gen is not None else 0)
            for p, v in acc.items():
                per.setdefault(p, []).append(v)
    finally:
        piqp.SparseSolver, updates.solve_lps_joint = original, lps
    n = steps - 1
    cpu = np.array(per["step (CPU)"])
    by_rounds = {int(r): (int(np.sum(np.array(rounds) == r)),
                          float(np.median(cpu[np.array(rounds) == r]))) for r in set(rounds)}
    return {"median": {p: float(np.median(v + [0.0] * (n - len(v)))) for p, v in per.items()},
            "rounds": rounds, "by_rounds": by_rounds, "iterations": iters,
            "fallbacks": loop.fallbacks}


def ab(masses: int, steps: int, options: dict) -> dict:
    """Two closed loops taking turns: the default and the default with ``options`` over its
    reduced solves' PIQP settings (see the module docstring)."""
    d = msd_adaptive.design(masses)
    ctrls = {"default": msd_adaptive.adaptive_controller(d),
             "variant": msd_adaptive.adaptive_controller(d)}
    loops = {k: Loop(d, c.step, steps) for k, c in ctrls.items()}
    for loop in loops.values():
        loop(0)
    gen = _rowgen(ctrls["variant"])
    attrs = {k[1:]: options.pop(k) for k in list(options) if k.startswith("@")}
    gen.reduced = {**gen.reduced, **options}
    for k, v in attrs.items():
        setattr(gen, k, v)
    gen._solver = None
    cpu: dict[str, list[float]] = {k: [] for k in loops}
    rounds: dict[str, list[int]] = {k: [] for k in loops}
    for k in range(1, steps):
        for label in (list(loops) if k % 2 else list(loops)[::-1]):
            c0 = time.process_time()
            loops[label](k)
            cpu[label].append(time.process_time() - c0)
            rounds[label].append(_rowgen(ctrls[label]).stats.rounds)
    wall = {k: np.array(v.times[1:]) for k, v in loops.items()}
    c = {k: np.array(v) for k, v in cpu.items()}
    du = float(np.max(np.abs(np.array(loops["default"].applied)
                             - np.array(loops["variant"].applied))))
    return {"wall": {k: float(np.median(v)) for k, v in wall.items()},
            "cpu": {k: float(np.median(v)) for k, v in c.items()},
            "cpu_ratio": float(np.median(c["default"] / c["variant"])),
            "rounds": rounds, "max_du": du,
            "fallbacks": {k: v.fallbacks for k, v in loops.items()}}


def round2(masses: int, steps: int, pairs: int) -> list[dict]:
    """DAQP on second-round reduced QPs, started from the first round (module docstring)."""
    import daqp
    import piqp

    import balustrade.backends.row_generation as rg
    recorded: list[dict] = []
    original = rg.RowGeneration._solve_reduced

    def record(self, q, A_eq, b_eq, G, h, solver=None):
        raw, s = original(self, q, A_eq, b_eq, G, h, solver)
        recorded.append({"P": self._P, "q": q.copy(), "A": A_eq.copy(), "b": b_eq.copy(),
                         "G": sp.csc_matrix(G).copy(), "h": h.copy(), "y": raw.y,
                         "round": self.stats.rounds})
        return raw, s

    rg.RowGeneration._solve_reduced = record
    try:
        d = msd_adaptive.design(masses)
        ctrl = msd_adaptive.adaptive_controller(d)
        loop = Loop(d, ctrl.step, steps)
        for k in range(steps):
            loop(k)
    finally:
        rg.RowGeneration._solve_reduced = original
    found = [(a, b) for a, b in zip(recorded, recorded[1:]) if b["round"] == a["round"] + 1]
    out = []
    for a, b in found[:pairs]:
        m0 = b["A"].shape[0]
        H = (b["P"] + sp.triu(b["P"], 1).T).toarray()
        A = np.vstack([b["A"].toarray(), b["G"].toarray()])
        sense = np.zeros(A.shape[0], dtype=np.intc)
        sense[:m0] = 5                                     # equality rows
        Gy = b["G"] @ a["y"]
        sense[m0 + np.flatnonzero(np.abs(Gy - b["h"]) <= 1e-8 * (1 + np.abs(b["h"])))] = 1
        model = daqp.Model()
        model.settings = {"primal_tol": 1e-10, "eta_prox": 1e-12}
        c0 = time.process_time()
        model.setup(H, b["q"].copy(), A, np.r_[b["b"], b["h"]],
                    np.r_[b["b"], np.full(b["h"].size, -1e30)], sense,
                    primal_start=a["y"].copy())
        c1 = time.process_time()
        x, _, flag, info = model.solve()
        c2 = time.process_time()
        s = piqp.SparseSolver()
        s.settings.verbose = False
        s.settings.eps_abs, s.settings.eps_rel = 1e-10, 1e-11
        s.settings.kkt_solver = piqp.KKTSolver.sparse_ldlt_ineq_cond
        c3 = time.process_time()
        s.setup(b["P"], b["q"], b["A"], b["b"], b["G"], None, b["h"])
        s.solve()
        c4 = time.process_time()
        P = b["P"].diagonal() > 0                           # the inputs: the weighed entries
        out.append({"rows": A.shape[0], "flag": int(flag), "daqp_iter": int(info["iterations"]),
                    "daqp_setup": c1 - c0, "daqp_solve": c2 - c1, "piqp": c4 - c3,
                    "piqp_iter": int(s.result.info.iter),
                    "dv": float(np.max(np.abs(np.asarray(x)[P] - np.asarray(s.result.x)[P])))})
    return out


def main(argv: list[str]) -> None:
    mode = argv[0] if argv else "split"
    masses = int(argv[1]) if len(argv) > 1 else 8
    steps = int(argv[2]) if len(argv) > 2 else 40
    print(f"load average {os.getloadavg()[0]:.1f} at the start")
    if mode == "split":
        r = split(masses, steps)
        print(f"{masses} masses, {steps - 1} timed steps, rounds per step "
              f"{np.bincount(r['rounds']).tolist()} (count of 0, 1, 2, … rounds), iterations "
              f"per reduced solve median {np.median(r['iterations']):.0f}, "
              f"fallbacks {r['fallbacks']}")
        for p, v in r["median"].items():
            print(f"  {p:<26} median {1e3 * v:8.2f} ms")
        for k, (count, med) in sorted(r["by_rounds"].items()):
            print(f"  steps with {k} round(s): {count}, median CPU {1e3 * med:.2f} ms")
    elif mode == "ab":
        options = ast.literal_eval(argv[3]) if len(argv) > 3 else {"preconditioner_iter": 10}
        print(f"{masses} masses, {steps - 1} timed steps taking turns; variant: {options} "
              "(keys with @: attributes of the row generation, others: its reduced solves' "
              "PIQP settings)")
        r = ab(masses, steps, dict(options))
        for k in r["wall"]:
            print(f"  {k:<8} median step wall {1e3 * r['wall'][k]:7.2f} ms  CPU "
                  f"{1e3 * r['cpu'][k]:7.2f} ms  rounds {np.bincount(r['rounds'][k]).tolist()}"
                  f"  fallbacks {r['fallbacks'][k]}")
        print(f"  median per-step CPU ratio default/variant {r['cpu_ratio']:.3f}; max |du| "
              f"{r['max_du']:.1e}")
    elif mode == "round2":
        r = round2(masses, steps, int(argv[3]) if len(argv) > 3 else 8)
        for x in r:
            print(f"  {x['rows']} rows: DAQP flag {x['flag']}, {x['daqp_iter']} iterations, "
                  f"set-up {1e3 * x['daqp_setup']:.1f} ms + solve {1e3 * x['daqp_solve']:.1f} "
                  f"ms CPU; PIQP {1e3 * x['piqp']:.1f} ms ({x['piqp_iter']} iterations); "
                  f"max |dv| {x['dv']:.1e}")
    print(f"load average {os.getloadavg()[0]:.1f} at the end")


if __name__ == "__main__":
    main(sys.argv[1:])
