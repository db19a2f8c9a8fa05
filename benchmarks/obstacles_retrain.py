"""Session 15: the §8.3 network retrained on the corrected (2.24) labels (``LABEL_RULE = 2``).

Trains the learning curve of :func:`balustrade.reproduce.obstacles.learning_curve` (the
reproduction's recipe: 5 × 32 softplus, ``∛h`` labels, Huber, 8× symmetry augmentation, the
fractions 1/8, 1/4, 1/2, 1 of the training rows) on a data set sampled with
``balustrade sample --config configs/obstacles-small.json``, plus one network on the first
``--matched`` training rows (the size of the network it replaces), and evaluates all of them
and the previous network (``--old-net``) on the new validation set. With ``--old-val`` (the
validation split sampled with ``problem_kwargs: {"braking_start": false}``, i.e. the labels
before the fix) it also compares the labels point by point and evaluates the old network
there. ``--seeds K`` trains both sizes with the training seeds 0..K−1 (the spread of the
recipe itself) and runs the reproduction's 5 quick closed loops (Algorithm 7.5, ``ρ = 0.5``,
70 steps) with each network; ``--exact-h`` computes the exact ``h`` (2.24) along the quick
loops of the full-data seed-0 network (:func:`~balustrade.reproduce.obstacles.exact_h_along`).
Writes ``retrain.json`` and the full-data seed-0 network ``obstacles_net.npz`` (what the full
reproduction trains from the same data) into ``--out``.

    PYTHONPATH=$PWD nice -n 10 .venv/bin/python benchmarks/obstacles_retrain.py \\
        --data out/obstacles-data --old-net out/old_net.npz \\
        --old-val out/obstacles-data-rule1/val --out out/retrain --seeds 5 --exact-h
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from balustrade.control.approximate import ApproximatePCBFFilter
from balustrade.learn.dataset import ShardedDataset
from balustrade.learn.export import to_casadi
from balustrade.learn.train import MLPModel
from balustrade.models.obstacle_car import obstacle_car, obstacle_setup
from balustrade.reproduce import obstacles as R


def quick_loops(model: MLPModel, mpc: R.NaiveMPC) -> list[dict]:
    """The reproduction's quick closed loops (``reproduce obstacles --quick``) with ``model``."""
    s = obstacle_setup()
    f = ApproximatePCBFFilter(obstacle_car(), s.U, to_casadi(model), rho=R.RHO,
                              target=R.FILTER_TARGET, network=model)
    return R.closed_loops(f, mpc)


def loop_summary(runs: list[dict]) -> dict:
    m = R.loop_metrics(runs)
    return {"min_signed_distance": [r["min_signed_distance"] for r in m["runs"].values()],
            "steps_input_changed": m["steps_input_changed"], "paths": m["paths"]}


def label_comparison(old: ShardedDataset, new: ShardedDataset) -> dict:
    """The same walk points labelled by both rules (the plan is the same seed, so the rows
    must coincide; checked)."""
    Xo, yo = old.arrays("h")
    Xn, yn = new.arrays("h")
    if Xo.shape != Xn.shape or not np.allclose(Xo, Xn, atol=0, rtol=0):
        return {"same_points": False, "n_old": len(yo), "n_new": len(yn)}
    d = yn - yo
    return {"same_points": True, "n": int(len(yn)),
            "lower": int(np.sum(d < -1e-9)), "higher": int(np.sum(d > 1e-9)),
            "largest_drop": float(d.min()), "largest_rise": float(d.max()),
            "unsafe_to_safe": int(np.sum((yo > 0) & (yn <= 0))),
            "safe_to_unsafe": int(np.sum((yo <= 0) & (yn > 0))),
            "positive_old": int(np.sum(yo > 0)), "positive_new": int(np.sum(yn > 0))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--old-net", type=Path, required=True)
    ap.add_argument("--old-val", type=Path)
    ap.add_argument("--matched", type=int, default=1823)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--seeds", type=int, default=0)
    ap.add_argument("--exact-h", action="store_true")
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    tr, va = ShardedDataset(a.data / "train"), ShardedDataset(a.data / "val")
    X, y = tr.arrays("h")
    Xv, yv = va.arrays("h")
    res: dict = {"data": {"train": int(len(y)), "val": int(len(yv)),
                          "train_in_S_PB": float(np.mean(y <= 0)),
                          "val_in_S_PB": float(np.mean(yv <= 0)),
                          "label_rule": tr.manifest()["config"].get("label_rule"),
                          "train_dropped": tr.dropped(), "val_dropped": va.dropped(),
                          "train_throughput": tr.throughput(),
                          "val_throughput": va.throughput()}}
    old = MLPModel.load(a.old_net)
    res["old_net_on_new_val"] = R.validation_errors(old, Xv, yv)
    if a.old_val is not None:
        ov = ShardedDataset(a.old_val)
        Xo, yo = ov.arrays("h")
        res["old_net_on_rule1_val"] = R.validation_errors(old, Xo, yo)
        res["val_labels_rule1_vs_rule2"] = label_comparison(ov, va)
    w, c = time.perf_counter(), time.process_time()
    curve, model = R.learning_curve(X, y, Xv, yv)
    res["learning_curve"] = curve
    res["curve_wall_s"], res["curve_cpu_s"] = time.perf_counter() - w, time.process_time() - c
    if a.matched < len(y):
        m = R.train_net(X[:a.matched], y[:a.matched], Xv, yv)
        res["matched_size"] = {"n_train": a.matched, **R.validation_errors(m, Xv, yv)}
    model.save(a.out / "obstacles_net.npz")
    mpc = R.NaiveMPC()
    res["old_net_loops"] = loop_summary(quick_loops(old, mpc))
    if a.seeds:
        res["seeds"] = []
        for n in (len(y), a.matched):
            for seed in range(a.seeds):
                m = R.train_net(X[:n], y[:n], Xv, yv, seed=seed)
                res["seeds"].append({"n_train": n, "seed": seed,
                                     **R.validation_errors(m, Xv, yv),
                                     **loop_summary(quick_loops(m, mpc))})
                print(json.dumps(res["seeds"][-1], default=str), flush=True)
    if a.exact_h:
        runs = quick_loops(model, mpc)
        res["new_net_loops"] = loop_summary(runs)
        w, c = time.perf_counter(), time.process_time()
        res["exact_h_along_new_net"] = R.exact_h_along(runs, model)
        res["exact_h_wall_s"], res["exact_h_cpu_s"] = (time.perf_counter() - w,
                                                       time.process_time() - c)
    (a.out / "retrain.json").write_text(json.dumps(res, indent=1, default=str))
    print(json.dumps({k: v for k, v in res.items() if k != "data"}, indent=1, default=str))
    print(json.dumps(res["data"], default=str))


if __name__ == "__main__":
    main()
