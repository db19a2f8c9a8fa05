"""``balustrade sample`` and ``balustrade train`` (registered by :mod:`balustrade.cli`).

Both take flags or ``--config FILE`` (JSON whose keys are the long flag names with ``_``,
e.g. ``{"grid_step": [0.01, 0.04], "workers": 8}``; flags given on the command line win).

Examples::

    balustrade sample --out out/pendulum-D --grid-step 0.01 0.04 --workers 8
    balustrade sample --out out/pendulum-D --scheduler tcp://head:8786   # same, on Dask
    balustrade sample --out out/geo --mode geometric --goals 4096 --line-step 0.01
    balustrade train --data out/pendulum-D --target h --widths 16 16 16 --out out/h.npz
    balustrade sample --config configs/obstacles-full.json --scheduler tcp://head:8786

A config may hold ``"problem_kwargs"`` (arguments of the problem factory, e.g.
``{"N": 10}``) and ``"splits"``: named datasets sampled by one command into ``OUT/<name>``,
each a dict of options overriding the others (e.g. the independent training and validation
sets of Section 8.3: ``{"train": {"goals": 150000, "seed": 1}, "val": {"goals": 75000,
"seed": 2, "x_seed": [...]}}``). An interrupted ``sample`` is resumed by running the same
command again (finished splits and chunks are skipped). At the end it prints the
throughput per core (points per core-second, recorded per run in each manifest).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

SAMPLE_DEFAULTS: dict[str, Any] = {
    "problem": "pendulum", "target": "fast-sqp", "mode": "grid", "lower": [-2.0, -8.0],
    "upper": [2.0, 8.0], "grid_step": [0.01, 0.04], "band": True, "cap": 10.0,
    "chunk_size": 500, "goals": 1024, "goals_per_chunk": 16, "line_step": 0.01, "seed": 0,
    "workers": None, "scheduler": None, "quiet": False, "cold": False, "scale": 1.5,
    "x_seed": None, "splits": None, "problem_kwargs": None,
}
TRAIN_DEFAULTS: dict[str, Any] = {
    "target": "h", "widths": [16, 16, 16], "epochs": 30, "lr": 5e-3, "batch_size": 8,
    "loss": "mse", "transform": None, "lr_schedule": None, "val_fraction": 0.1, "seed": 0,
    "verbose": True,
}


def _merge(args: argparse.Namespace, defaults: dict[str, Any]) -> dict[str, Any]:
    cfg = dict(defaults)
    if getattr(args, "config", None):
        from_file = json.loads(Path(args.config).read_text())
        unknown = set(from_file) - set(defaults) - {"out", "data"}
        if unknown:
            from balustrade.errors import BalustradeError

            renamed = {"solver": "target"}  # keys renamed when solvers became targets
            hints = [f"{k!r} is now {renamed[k]!r}" for k in sorted(unknown) if k in renamed]
            raise BalustradeError(f"{args.config}: unknown keys {sorted(unknown)}"
                                  + (f" ({'; '.join(hints)})" if hints else ""))
        cfg.update(from_file)
    for key, value in vars(args).items():
        if value is not None and key not in ("func", "config", "command"):
            cfg[key] = value
    return cfg


def _cmd_sample(args: argparse.Namespace) -> int:
    from balustrade.errors import BalustradeError
    from balustrade.learn.dataset import run_sampling
    from balustrade.learn.executors import make_executor
    from balustrade.learn.sampler import ProblemSpec

    cfg = _merge(args, SAMPLE_DEFAULTS)
    if not cfg.get("out"):
        raise BalustradeError("sample: --out (or 'out' in the config file) is required")
    splits = cfg.pop("splits", None)
    if splits is not None and not isinstance(splits, dict):
        raise BalustradeError("sample: 'splits' must map dataset names to option dicts")
    jobs = ([(Path(cfg["out"]) / name, {**cfg, **(opts or {})})
             for name, opts in splits.items()] if splits else [(Path(cfg["out"]), cfg)])
    with make_executor(cfg["workers"], cfg["scheduler"]) as ex:
        for out, job in jobs:
            spec = ProblemSpec.of(job["problem"], target=job["target"],
                                  **(job["problem_kwargs"] or {}))
            chunks, plan = _plan(spec.build().X, job)
            ds = run_sampling(out, spec, chunks, ex, plan, progress=not job["quiet"])
            if not job["quiet"]:
                rows = sum(ds.completed().values())
                tp = ds.throughput()
                rate = tp["points_per_core_s"]
                print(f"{rows} samples in {len(chunks)} shards at {out.resolve()}; "
                      f"throughput {rate:.3g} points per core-second" if rate else
                      f"{rows} samples in {len(chunks)} shards at {out.resolve()}")
                dropped = ds.dropped()
                if dropped:
                    print(f"dropped (not used for training): {dropped}")
    return 0


def _plan(X: Any, cfg: dict[str, Any]) -> tuple[list, dict[str, Any]]:
    from balustrade.errors import BalustradeError
    from balustrade.learn.dataset import geometric_plan, grid_plan

    if cfg["mode"] == "grid":
        return grid_plan(X, cfg["lower"], cfg["upper"], cfg["grid_step"],
                         int(cfg["chunk_size"]), cfg["cap"], bool(cfg["band"]),
                         warm=not cfg["cold"])
    if cfg["mode"] == "geometric":
        return geometric_plan(X, int(cfg["goals"]), int(cfg["goals_per_chunk"]),
                              float(cfg["line_step"]), int(cfg["seed"]), cfg["cap"],
                              float(cfg["scale"]), cfg["x_seed"])
    raise BalustradeError(f"sample: unknown mode {cfg['mode']!r} (grid | geometric)")


def _cmd_train(args: argparse.Namespace) -> int:
    from balustrade.errors import BalustradeError
    from balustrade.learn.dataset import ShardedDataset
    from balustrade.learn.train import TrainConfig, train

    cfg = _merge(args, TRAIN_DEFAULTS)
    if not cfg.get("data") or not cfg.get("out"):
        raise BalustradeError("train: --data and --out are required")
    X, y = ShardedDataset(cfg["data"]).arrays(cfg["target"])
    tc = TrainConfig(widths=tuple(cfg["widths"]), epochs=int(cfg["epochs"]), lr=float(cfg["lr"]),
                     batch_size=int(cfg["batch_size"]), loss=cfg["loss"],
                     output_transform=cfg["transform"], lr_schedule=cfg["lr_schedule"],
                     val_fraction=float(cfg["val_fraction"]),
                     seed=int(cfg["seed"]))
    model = train(X, y, tc, verbose=bool(cfg["verbose"]))
    model.save(cfg["out"])
    val = model.history.get("val_mse_h", [])
    print(f"trained on {len(y)} samples; validation MSE of ĥ "
          f"{val[-1] if val else float('nan'):.4g}; model written to {cfg['out']}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``sample`` and ``train`` subcommands."""
    s = sub.add_parser("sample", help="sample (extended) PCBF values into a dataset "
                       "(Algorithm 7.6 or a grid), resumable, local or on Dask")
    s.add_argument("--config", help="JSON file with any of the options below")
    s.add_argument("--out", help="dataset directory (Parquet shards + manifest.json)")
    s.add_argument("--problem", help="'pendulum', 'obstacles' or 'package.module:function'")
    s.add_argument("--target", help="solver target (balustrade.backends presets): fast-sqp "
                   "(default; warm-started line walks, the sampling-cold target for cold "
                   "starts and failed warm solves) or exact (interior point, warm and cold)")
    s.add_argument("--mode", choices=["grid", "geometric"])
    s.add_argument("--lower", type=float, nargs="+", help="grid box lower corner")
    s.add_argument("--upper", type=float, nargs="+", help="grid box upper corner")
    s.add_argument("--grid-step", dest="grid_step", type=float, nargs="+")
    s.add_argument("--no-band", dest="band", action="store_const", const=False,
                   help="no extra points near the constraints")
    s.add_argument("--cap", type=float, help="reject samples with h_PB above this")
    s.add_argument("--chunk-size", dest="chunk_size", type=int)
    s.add_argument("--goals", type=int, help="geometric mode: number of goal points")
    s.add_argument("--goals-per-chunk", dest="goals_per_chunk", type=int)
    s.add_argument("--line-step", dest="line_step", type=float, help="geometric mode: d")
    s.add_argument("--seed", type=int)
    s.add_argument("--scale", type=float, help="geometric mode: goals in scale × the box")
    s.add_argument("--x-seed", dest="x_seed", type=float, nargs="+",
                   help="geometric mode: the initial seed state (default: the origin)")
    s.add_argument("--workers", type=int, help="local processes (default: all cores)")
    s.add_argument("--scheduler", help="Dask scheduler address (tcp://host:8786)")
    s.add_argument("--cold", action="store_const", const=True, help="no warm starts")
    s.add_argument("--quiet", action="store_const", const=True)
    s.set_defaults(func=_cmd_sample)

    t = sub.add_parser("train", help="fit a softplus MLP ĥ to a sampled dataset (PyTorch)")
    t.add_argument("--config", help="JSON file with any of the options below")
    t.add_argument("--data", help="dataset directory written by 'balustrade sample'")
    t.add_argument("--out", help="model file (.npz)")
    t.add_argument("--target", choices=["h", "h_pb"])
    t.add_argument("--widths", type=int, nargs="+")
    t.add_argument("--epochs", type=int)
    t.add_argument("--lr", type=float)
    t.add_argument("--batch-size", dest="batch_size", type=int)
    t.add_argument("--loss", choices=["mse", "huber"])
    t.add_argument("--transform", choices=["cbrt"],
                   help="fit the cube root of the target, ĥ = net³ (Section 8.3)")
    t.add_argument("--lr-schedule", dest="lr_schedule", choices=["cosine"],
                   help="cosine annealing of the learning rate to 0 (default: constant)")
    t.add_argument("--val-fraction", dest="val_fraction", type=float)
    t.add_argument("--seed", type=int)
    t.add_argument("--quiet", dest="verbose", action="store_const", const=False)
    t.set_defaults(func=_cmd_train)


if __name__ == "__main__":  # pragma: no cover
    from balustrade.cli import main

    sys.exit(main())
