"""Algorithms 5.2 and 6.4 on the lane change (``converging``) in Python (or, with ``--c``, on
the emitted C) on many seeds, for the 50-seed table of docs/vehicles.md ("Session 15: 50
Python seeds"): the must-shows of :func:`~balustrade.reproduce.lane_change.run_metrics` per
run, the per-step wall and CPU times, statuses, fallbacks, inputs and states (for comparing
Python with C on the same seeds).

``python benchmarks/lane_python_seeds.py OUT_DIR SEEDS [--c]``: ``SEEDS`` comma-separated or
``A-B``; resumable (one JSON per seed and side in ``OUT_DIR``, an existing file is skipped),
so several processes can share seeds (``0-24`` and ``25-49``).
``python benchmarks/lane_python_seeds.py summary OUT_DIR``: the table (median / p90 / worst
step, steps >= 1 s, the run checks, fallbacks, statuses not ``ok``).
``python benchmarks/lane_python_seeds.py compare PY_DIR C_DIR``: per seed and algorithm the
largest input and state difference and the steps whose statuses or fallbacks differ."""

from __future__ import annotations

import json
import os
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

from balustrade.reproduce import lane_change as lc

KEYS = {"robust": "h_r", "multiobjective": "h_tilde"}


def _seeds(text: str) -> list[int]:
    if "-" in text:
        a, b = text.split("-")
        return list(range(int(a), int(b) + 1))
    return [int(s) for s in text.split(",")]


def closed_loop(ctrl: object, d: lc.BicycleDesign, ws: np.ndarray) -> dict:
    """:func:`~balustrade.reproduce.lane_change.closed_loop` with the CPU time of each step
    beside its wall time (the machine is shared)."""
    cpu: list[float] = []
    step = ctrl.step

    def timed(x: np.ndarray, u: np.ndarray) -> tuple:
        start = time.process_time()
        out = step(x, u)
        cpu.append(time.process_time() - start)
        return out

    ctrl.step = timed  # type: ignore[method-assign]
    try:
        r = lc.closed_loop(ctrl, d, ws)
    finally:
        del ctrl.step
    r["cpu"] = np.array(cpu)
    return r


def run(out: Path, seeds: list[int], c: bool) -> None:
    cfg = lc.config("converging")
    d = lc.design(cfg)
    ctrls = lc.controllers(d, rho=cfg.rho)
    if c:
        from balustrade.codegen import accelerate

        ctrls = {k: accelerate(v) for k, v in ctrls.items()}
    out.mkdir(parents=True, exist_ok=True)
    for seed in seeds:
        path = out / f"seed{seed:03d}.json"
        if path.exists():
            continue
        ws = lc.disturbances(d, seed, lc.STEPS)
        row: dict = {"seed": seed, "side": "c" if c else "python"}
        for name, ctrl in ctrls.items():
            r = closed_loop(ctrl, d, ws)
            row[name] = {"metrics": lc.run_metrics(r, d, KEYS[name]),
                         "times": r["times"].tolist(), "cpu": r["cpu"].tolist(),
                         "statuses": r["statuses"], "fallbacks": r["fallbacks"],
                         "inputs": r["inputs"].tolist(), "states": r["states"].tolist(),
                         KEYS[name]: r[KEYS[name]].tolist()}
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(json.dumps(row, default=lc._json))
        os.replace(tmp, path)
        w = max(max(row[k]["times"]) for k in ctrls)
        print(f"seed {seed} done, worst step {1e3 * w:.0f} ms, load "
              f"{os.getloadavg()[0]:.1f}", flush=True)


def _rows(folder: str) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted(Path(folder).glob("seed*.json"))]


def summary(folder: str) -> None:
    rows = _rows(folder)
    print(f"{folder}: {len(rows)} seeds ({[r['seed'] for r in rows][:3]}…)")
    for name in KEYS:
        runs = [r[name] for r in rows]
        t = 1e3 * np.concatenate([x["times"] for x in runs])
        cpu = 1e3 * np.concatenate([x["cpu"] for x in runs])
        m = [x["metrics"] for x in runs]
        worst = max(((max(x["times"]), r["seed"], int(np.argmax(x["times"])))
                     for r, x in zip(rows, runs)))
        st = Counter(s for x in runs for s in x["statuses"] if s != "ok")
        fb = [(r["seed"], k) for r, x in zip(rows, runs)
              for k, f in enumerate(x["fallbacks"]) if f is not None]
        print(f"  {name}: wall median / p90 / worst "
              + " / ".join(f"{v:.1f}" for v in np.percentile(t, [50, 90, 100]))
              + f" ms (worst seed {worst[1]} step {worst[2]}); cpu median / p90 / worst "
              + " / ".join(f"{v:.1f}" for v in np.percentile(cpu, [50, 90, 100]))
              + f" ms; >= 1 s wall {int((t >= 1000).sum())}, cpu {int((cpu >= 1000).sum())}; "
              f"non-increasing {sum(x['non_increasing'] for x in m)}, largest rise "
              f"{max(x['largest_increase'] for x in m):.2g}, converged "
              f"{sum(x['converged'] for x in m)}, entered S_r "
              f"{sum(x['entered_S_r_at'] >= 0 for x in m)} "
              f"(latest {max(x['entered_S_r_at'] for x in m)}), X kept "
              f"{sum(x['X_kept_after_S_r'] for x in m)}, peak a_lat median "
              f"{np.median([x['peak_lateral_acceleration'] for x in m]):.3f}; fallbacks "
              f"{len(fb)} {fb}; not ok {sum(st.values())} {dict(st)}")
        by_step = Counter(k for x in runs for k, s in enumerate(x["statuses"]) if s != "ok")
        print(f"    not-ok steps by step index: {dict(sorted(by_step.items()))}; after step 0: "
              + ", ".join(f"seed {r['seed']} k={k} {s}" for r, x in zip(rows, runs)
                          for k, s in enumerate(x["statuses"]) if s != "ok" and k > 0))
        worst_cpu = sorted(((max(x["cpu"]), r["seed"], int(np.argmax(x["cpu"])))
                            for r, x in zip(rows, runs)), reverse=True)[:3]
        print("    largest CPU steps: " + ", ".join(f"{1e3 * c:.0f} ms (seed {s}, step {k})"
                                                   for c, s, k in worst_cpu))


def compare(py_dir: str, c_dir: str) -> None:
    py = {r["seed"]: r for r in _rows(py_dir)}
    for c in _rows(c_dir):
        p = py.get(c["seed"])
        if p is None:
            continue
        for name in KEYS:
            a, b = p[name], c[name]
            du = np.abs(np.array(a["inputs"]) - np.array(b["inputs"])).max()
            dx = np.abs(np.array(a["states"]) - np.array(b["states"])).max()
            st = [k for k, (x, y) in enumerate(zip(a["statuses"], b["statuses"])) if x != y]
            fb = [k for k, (x, y) in enumerate(zip(a["fallbacks"], b["fallbacks"])) if x != y]
            print(f"seed {c['seed']} {name}: max input diff {du:.3g}, state {dx:.3g}, "
                  f"status mismatches {st}, fallback mismatches {fb}; not ok python "
                  f"{sum(s != 'ok' for s in a['statuses'])}, C "
                  f"{sum(s != 'ok' for s in b['statuses'])}")


def main(argv: list[str]) -> None:
    if argv[0] == "summary":
        for folder in argv[1:]:
            summary(folder)
    elif argv[0] == "compare":
        compare(argv[1], argv[2])
    else:
        run(Path(argv[0]), _seeds(argv[1]), "--c" in argv[2:])


if __name__ == "__main__":
    main(sys.argv[1:])
