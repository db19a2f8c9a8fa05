"""Algorithm 6.4 on the lane change (``converging``) with variants of the (6.15) solve chain
and start, for the worst-step study of docs/vehicles.md, "Session 14".

``python benchmarks/lane_chain_variants.py VARIANT SEEDS OUT.json [c]``: the closed loops of
``VARIANT`` on the comma-separated ``SEEDS`` (200 steps each), in Python or, with ``c``, on
the emitted C (:func:`~balustrade.codegen.accelerate`); per seed the step times, statuses,
fallbacks, ``h_cand`` and :func:`~balustrade.reproduce.lane_change.run_metrics`
(``... summary A.json B.json``: the table of docs/vehicles.md). Run the
variants to compare at the same time (same load). Variants (all ``robust-sqp`` options and
the compact lowering; ``(5.15)`` always on ``robust-sqp``):

* ``base``: ``robust-sqp`` (SQP 500 iterations → eigen-reflect SQP → interior point);
* ``cd``: ``base`` with ``candidate_duals=True`` (ordinary (6.15) from the candidate with the
  previous multipliers);
* ``cs``: ``base`` with ``candidate_second=True`` (a failed ordinary (6.15) tried once more
  from the candidate with the previous multipliers before the cold retries);
* ``ipfirst``: interior point before the eigen-reflect retry (idea 1, every step);
* ``capM``: SQP capped at ``M`` iterations → interior point → eigen-reflect (500);
* ``cbM``: SQP and eigen-reflect retry capped at ``M`` iterations, usual order (idea 3).
"""

from __future__ import annotations

import json
import sys

from balustrade.backends.targets import Target
from balustrade.control.multiobjective import MultiobjectivePCBFController
from balustrade.reproduce import lane_change as lc

_REFLECT = ("sqpmethod", {"convexify_strategy": "eigen-reflect"})


def variant(name: str) -> Target | str:
    """The (6.15) target of ``name`` (module docstring)."""
    if name in ("base", "cd", "cs"):
        return lc.TARGET
    opts = {"lowering": "as-emitted"}
    if name == "ipfirst":
        return Target("casadi", "sqpmethod", {**opts, "max_iter": 500},
                      retries=(("ipopt", {}), _REFLECT), name="v-ipfirst")
    if name.startswith("cb"):
        return Target("casadi", "sqpmethod", {**opts, "max_iter": int(name[2:])},
                      retries=(_REFLECT, ("ipopt", {})), name=f"v-{name}")
    if name.startswith("cap"):
        return Target("casadi", "sqpmethod", {**opts, "max_iter": int(name[3:])},
                      retries=(("ipopt", {}), ("sqpmethod", {"convexify_strategy":
                                                             "eigen-reflect", "max_iter": 500})),
                      name=f"v-{name}")
    raise SystemExit(f"unknown variant {name!r}")


def summary(paths: list[str]) -> None:
    """Per result file: median / 90th / 95th / 99th percentile / worst step, steps >= 100 ms
    and >= 1 s, the time of all steps, steps not ``ok`` and the run checks."""
    import numpy as np

    for path in paths:
        with open(path) as f:
            rows = json.load(f)
        t = 1e3 * np.concatenate([r["times"] for r in rows])
        m = [r["metrics"] for r in rows]
        print(f"{path}: {len(rows)} seeds; median / p90 / p95 / p99 / worst "
              + " / ".join(f"{v:.1f}" for v in np.percentile(t, [50, 90, 95, 99, 100]))
              + f" ms; >=100 ms {int((t >= 100).sum())}, >=1 s {int((t >= 1000).sum())}; "
              f"all steps {t.sum() / 1e3:.1f} s; not ok {sum(x['not_ok'] for x in m)}; "
              f"non-increasing {all(x['non_increasing'] for x in m)}, converged "
              f"{all(x['converged'] for x in m)}, X kept "
              f"{all(x['X_kept_after_S_r'] for x in m)}")


def main(argv: list[str]) -> None:
    if argv[0] == "summary":
        summary(argv[1:])
        return
    name, seeds, out = argv[0], [int(s) for s in argv[1].split(",")], argv[2]
    cfg = lc.config("converging")
    d = lc.design(cfg)
    ctrl = MultiobjectivePCBFController.build(
        d.system, d.X, d.U, d.cbf, d.pi_f, d.N, d.deltas, d.error, d.alpha_f, rho=cfg.rho,
        target=variant(name), slack_target=lc.TARGET, running_sum=lc.RUNNING_SUM,
        candidate_duals=name == "cd", candidate_second=name == "cs")
    if len(argv) > 3 and argv[3] == "c":
        from balustrade.codegen import accelerate

        ctrl = accelerate(ctrl)
    rows = []
    for seed in seeds:
        r = lc.closed_loop(ctrl, d, lc.disturbances(d, seed, lc.STEPS))
        rows.append({"seed": seed, "times": r["times"].tolist(), "statuses": r["statuses"],
                     "fallbacks": r["fallbacks"], "h_cand": r["h_cand"].tolist(),
                     "metrics": lc.run_metrics(r, d, "h_tilde")})
        print(name, seed, f"worst {1e3 * r['times'].max():.0f} ms", flush=True)
    with open(out, "w") as f:
        json.dump(rows, f, default=lc._json)


if __name__ == "__main__":
    main(sys.argv[1:])
