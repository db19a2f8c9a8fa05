"""Session 15: the §8.3 network retrained on the corrected (2.24) labels (``LABEL_RULE = 2``).

Trains the learning curve of :func:`balustrade.reproduce.obstacles.learning_curve` (the
reproduction's recipe: 5 × 32 softplus, ``∛h`` labels, Huber, 8× symmetry augmentation, the
fractions 1/8, 1/4, 1/2, 1 of the training rows) on a data set sampled with
``balustrade sample --config configs/obstacles-small.json``, plus one network on the first
``--matched`` training rows (the size of the network it replaces), and evaluates all of them
and the previous network (``--old-net``) on the new validation set. With ``--old-val`` (the
validation split sampled with ``problem_kwargs: {"braking_start": false}``, i.e. the labels
before the fix) it also compares the labels point by point and evaluates the old network
there. Writes ``retrain.json`` and the full-data network ``obstacles_net.npz`` into ``--out``.

    PYTHONPATH=$PWD nice -n 10 .venv/bin/python benchmarks/obstacles_retrain.py \\
        --data out/obstacles-data --old-net out/old_net.npz \\
        --old-val out/obstacles-data-rule1/val --out out/retrain
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from balustrade.learn.dataset import ShardedDataset
from balustrade.learn.train import MLPModel
from balustrade.reproduce import obstacles as R


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
    (a.out / "retrain.json").write_text(json.dumps(res, indent=1, default=str))
    print(json.dumps({k: v for k, v in res.items() if k != "data"}, indent=1, default=str))
    print(json.dumps(res["data"], default=str))


if __name__ == "__main__":
    main()
