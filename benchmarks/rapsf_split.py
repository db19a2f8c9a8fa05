"""Where one step of Algorithm 4.1 (the RAPSF, thesis Chapter 4, SPEC §2.21) spends its time,
for the designs of ``reproduce msd-adaptive`` (3 masses: contractive polytope 𝕏₀; 8 masses:
contractive parallelotope), against the cvxpy transcription of (4.5) rebuilt every step
(:class:`benchmarks.bench_rapsf.RebuiltCvxpy`) in the same run (docs/adaptive.md, "Speed")::

    PYTHONPATH=$PWD python -m benchmarks.rapsf_split [masses] [steps]

Two closed loops with the same ``θ*`` and disturbances (:class:`benchmarks.bench_rapsf.Loop`):
the controller on ``fast-convex`` and the baseline, taking turns every step. The controller's
own bound methods are wrapped with timers (instance attributes only, nothing else changes):

* ``estimator LPs`` — the HiGHS run of the box update's ``2q`` support LPs (only on steps
  whose transition cuts ``Θ_{k−1}``);
* ``estimator, rest`` — the rest of ``BoxUpdate.update`` (the non-falsified rows (4.7), the
  vertex bound, the record);
* ``s_jr of a new Θ_k`` — vertices and support constants (SPEC §2.20) when ``Θ_k`` changed;
* ``nesting check`` — the rest of the parameter update (``Θ_k ⊆ Θ_{k−1}`` at the vertices);
* ``QP solve`` — the solver engine's run (PIQP's data update and its interior-point solve);
  0 when (4.5) is solved by row generation (8 masses), whose parts are:
* ``rowgen: PIQP set-up`` / ``rowgen: PIQP update`` — a new solver for a round with new
  rows, resp. the kept one's data update for a round with the last round's rows;
* ``rowgen: PIQP solves`` — the interior-point solves of the reduced QPs (all rounds);
* ``rowgen: all-row check`` — every inequality row at each round's optimum (one product);
* ``rowgen: rest`` — the rest of the row generation (values of ``A``, ``G[rows]``, the
  working set, the most violated rows, the multipliers of the full QP);
* ``QP data`` — the rest of the backend's ``solve`` (parameter packing, ``q``, ``b``,
  ``A(p)``, the :class:`~balustrade.backends.Solution` with its duals);
* ``step, rest`` — Algorithm 4.1's bookkeeping (plan, ``StepInfo``).

Medians over the timed steps (the first, which compiles, is not timed); the enlargement
(4.8)–(4.10) does not run per step in this design (it is computed after the run).
"""

from __future__ import annotations

import sys

import numpy as np

import balustrade.estimate.updates as updates
from balustrade.reproduce import msd_adaptive
from benchmarks.bench_rapsf import GOAL_S, Loop, RebuiltCvxpy
from benchmarks.bench_rapsf import timed_into as _timed

ROWGEN_PARTS = ["rowgen: PIQP set-up", "rowgen: PIQP update", "rowgen: PIQP solves",
                "rowgen: all-row check", "rowgen: rest"]
PARTS = ["estimator LPs", "estimator, rest", "s_jr of a new Θ_k", "nesting check",
         "QP solve", *ROWGEN_PARTS, "QP data", "step, rest"]


def _timed_piqp(acc: dict) -> tuple[object, object]:
    """``piqp.SparseSolver`` replaced (in the ``piqp`` module, which row generation imports
    per round) by a subclass timing ``setup``, ``update`` and ``solve`` into ``acc``;
    returns the module and the original class (to put back)."""
    import piqp

    original = piqp.SparseSolver

    class Timed(original):
        def setup(self, *a, **kw):
            return _timed(super().setup, acc, "rowgen: PIQP set-up")(*a, **kw)

        def update(self, *a, **kw):
            return _timed(super().update, acc, "rowgen: PIQP update")(*a, **kw)

        def solve(self):
            return _timed(super().solve, acc, "rowgen: PIQP solves")()

    piqp.SparseSolver = Timed
    return piqp, original


def split(masses: int, steps: int) -> dict:
    """Per-part medians (seconds) of the ``fast-convex`` step and the baseline's median step
    on ``steps`` closed-loop states, with the largest input difference between the two."""
    d = msd_adaptive.design(masses)
    ctrl = msd_adaptive.adaptive_controller(d, target="fast-convex")
    baseline = RebuiltCvxpy(d)
    loop = Loop(d, ctrl.step, steps)
    base = Loop(d, lambda x, u_p: (baseline.step(x, u_p), None), steps)
    loop(0)
    base(0)
    acc: dict[str, float] = {}
    lps = updates.solve_lps_joint
    updates.solve_lps_joint = _timed(lps, acc, "estimator LPs")
    piqp, solver_class = _timed_piqp(acc)
    try:
        ctrl.estimator.update = _timed(ctrl.estimator.update, acc, "estimator")
        ctrl._update_theta = _timed(ctrl._update_theta, acc, "theta update")
        ctrl._set_theta = _timed(ctrl._set_theta, acc, "s_jr of a new Θ_k")
        for compiled in ctrl._compiled.values():
            compiled.solve = _timed(compiled.solve, acc, "backend solve")
            compiled.engine.run = _timed(compiled.engine.run, acc, "QP solve")
            if compiled.rowgen is not None:
                gen = compiled.rowgen
                gen.run = _timed(gen.run, acc, "rowgen")
                gen._rows_at = _timed(gen._rows_at, acc, "rowgen: all-row check")
        per: dict[str, list[float]] = {k: [] for k in ["step", *PARTS]}
        rounds: list[int] = []       # row-generation rounds per step (0: none)
        for k in range(1, steps):
            base(k)                 # its own BoxUpdate's LPs are not the controller's
            acc.clear()
            loop(k)
            g = acc.get
            acc["estimator, rest"] = g("estimator", 0.0) - g("estimator LPs", 0.0)
            acc["nesting check"] = g("theta update", 0.0) - g("estimator", 0.0) \
                - g("s_jr of a new Θ_k", 0.0)
            acc["rowgen: rest"] = g("rowgen", 0.0) - sum(g(p, 0.0) for p in ROWGEN_PARTS[:-1])
            acc["QP data"] = g("backend solve", 0.0) - g("QP solve", 0.0) - g("rowgen", 0.0)
            acc["step, rest"] = loop.times[-1] - g("theta update", 0.0) \
                - g("backend solve", 0.0)
            per["step"].append(loop.times[-1])
            gens = [c.rowgen for c in ctrl._compiled.values()
                    if getattr(c, "rowgen", None) is not None]
            rounds.append(gens[0].stats.rounds if gens else 0)
            for p in PARTS:
                per[p].append(acc.get(p, 0.0))
    finally:
        updates.solve_lps_joint = lps
        piqp.SparseSolver = solver_class
    du = float(np.max(np.abs(np.array(loop.applied) - np.array(base.applied))))
    return {"masses": masses, "steps": steps - 1,
            "median": {k: float(np.median(v)) for k, v in per.items()},
            "mean": {k: float(np.mean(v)) for k, v in per.items()},
            "baseline_median": float(np.median(base.times[1:])),
            "max_du_vs_baseline": du, "fallbacks": loop.fallbacks,
            "lp_steps": sum(r.lps > 0 for r in ctrl.estimator.history),
            "rounds": rounds}


def main(argv: list[str]) -> None:
    masses = int(argv[0]) if argv else 3
    steps = int(argv[1]) if len(argv) > 1 else 150
    r = split(masses, steps)
    med, mean = r["median"], r["mean"]
    target = "fast-convex"
    if max(r["rounds"]) > 0:
        target = (f"fast-convex-rowgen, rounds per step {np.bincount(r['rounds']).tolist()} "
                  "(count of 0, 1, 2, … rounds)")
    print(f"{masses} masses, {r['steps']} steps ({target}; {r['lp_steps']} steps with "
          f"estimator LPs, {r['fallbacks']} fallbacks)")
    for k in ["step", *PARTS]:
        print(f"  {k:<22} median {1e3 * med[k]:9.3f} ms   mean {1e3 * mean[k]:9.3f} ms")
    print(f"  cvxpy rebuilt every step: median {1e3 * r['baseline_median']:.3f} ms, ratio "
          f"{r['baseline_median'] / med['step']:.1f}x; goal {1e3 * GOAL_S[masses]:.0f} ms; "
          f"max |du| vs baseline {r['max_du_vs_baseline']:.2g}")


if __name__ == "__main__":
    main(sys.argv[1:])
