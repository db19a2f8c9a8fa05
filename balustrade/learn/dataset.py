"""A resumable, sharded on-disk dataset of samples (Parquet shards + a JSON manifest).

Layout of a dataset directory::

    manifest.json          # config (what is sampled, how), plan size, completed chunks
    shard-000000.parquet   # the rows of chunk 0 (columns x0..x{n-1}, h, h_pb, h_bar, ...)
    shard-000001.parquet
    ...

Work is split into :class:`~balustrade.learn.sampler.Chunk` s with deterministic content
and seeds, so a chunk computed twice gives the same rows. Every finished chunk is written
as one shard through a temporary file and an atomic ``os.replace``; only then is its id
added to the manifest (itself replaced atomically). An interrupted run (killed process,
failure) therefore leaves complete shards and a manifest listing a subset of them; running
the same plan again skips the listed chunks and recomputes the others, overwriting any
orphan shard of an unlisted chunk. The result has every row exactly once.

Parquet rather than Zarr (docs/approximate.md): samples are rows of mixed types (floats,
flags, iteration counts), appended in independent pieces by chunk; a directory of Parquet
files is a standard dataset for pyarrow, pandas, polars, DuckDB and Spark, and pyarrow is
already the one dependency needed.
"""

from __future__ import annotations

import json
import os
import time
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from balustrade._checks import as_float_array, as_vector
from balustrade.errors import BalustradeError
from balustrade.learn.executors import Executor, SerialExecutor
from balustrade.learn.progress import Progress
from balustrade.learn.sampler import (
    Chunk,
    ProblemSpec,
    band_points,
    run_chunk,
    snake_grid,
    sobol_goals,
)

MANIFEST = "manifest.json"
FORMAT = "balustrade-samples/1"
#: How labels are computed; stored in the manifest so a dataset sampled under an older rule
#: refuses to resume instead of mixing labels. 2: (2.24) is solved once more from the
#: problems' ``slack_guess`` where the walk's solve did not place x in S_PB (session 15);
#: 3: that retry counts only when ``optimal`` (session 15, review R3).
LABEL_RULE = 3


class InterruptedRun(BalustradeError):
    """Raised by :func:`run_sampling` when asked to stop after ``stop_after`` chunks
    (to test resumption) — the dataset is left as after a crash."""


def _atomic_write_bytes(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    with open(tmp, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


class ShardedDataset:
    """A dataset directory: :meth:`write_shard`, :meth:`completed`, :meth:`read`."""

    def __init__(self, path: str | Path):
        self.path = Path(path)

    # -- manifest --------------------------------------------------------------------------
    @property
    def manifest_path(self) -> Path:
        return self.path / MANIFEST

    def manifest(self) -> dict[str, Any]:
        if not self.manifest_path.exists():
            return {}
        return json.loads(self.manifest_path.read_text())

    def _write_manifest(self, manifest: dict[str, Any]) -> None:
        _atomic_write_bytes(self.manifest_path, json.dumps(manifest, indent=1).encode())

    def init(self, config: dict[str, Any], n_chunks: int) -> None:
        """Create the dataset, or check that an existing one was made with ``config``."""
        self.path.mkdir(parents=True, exist_ok=True)
        old = self.manifest()
        if old:
            if old.get("config") != config or old.get("n_chunks") != n_chunks:
                was = {"n_chunks": old.get("n_chunks"), **(old.get("config") or {})}
                now = {"n_chunks": n_chunks, **config}
                differ = ", ".join(f"{k}: {was.get(k, 'none')!r} vs {now.get(k, 'none')!r}"
                                   for k in sorted(set(was) | set(now))
                                   if was.get(k) != now.get(k))
                raise BalustradeError(
                    f"{self.path}: existing dataset was sampled with a different configuration "
                    f"({differ}); use another directory (or delete it) to start over")
            return
        self._write_manifest({"format": FORMAT, "config": config, "n_chunks": n_chunks,
                              "completed": {}})

    def completed(self) -> dict[int, int]:
        """Completed chunk ids → row counts."""
        return {int(k): int(v) for k, v in self.manifest().get("completed", {}).items()}

    @property
    def done(self) -> bool:
        m = self.manifest()
        return bool(m) and len(m.get("completed", {})) == m.get("n_chunks")

    def shard_path(self, chunk_id: int) -> Path:
        return self.path / f"shard-{chunk_id:06d}.parquet"

    def write_shard(self, chunk_id: int, columns: dict[str, np.ndarray]) -> None:
        """Write one chunk's rows atomically, then record the chunk in the manifest."""
        import pyarrow as pa
        import pyarrow.parquet as pq

        table = pa.table({k: np.asarray(v) for k, v in columns.items()})
        sink = pa.BufferOutputStream()
        pq.write_table(table, sink)
        _atomic_write_bytes(self.shard_path(chunk_id), sink.getvalue().to_pybytes())
        manifest = self.manifest()
        manifest["completed"][str(chunk_id)] = int(table.num_rows)
        self._write_manifest(manifest)

    # -- reading ---------------------------------------------------------------------------
    def read(self, columns: Sequence[str] | None = None) -> dict[str, np.ndarray]:
        """All rows of the completed chunks, in chunk order, as numpy columns."""
        import pyarrow as pa
        import pyarrow.parquet as pq

        ids = sorted(self.completed())
        if not ids:
            return {}
        tables = [pq.read_table(self.shard_path(i), columns=list(columns) if columns else None)
                  for i in ids]
        table = pa.concat_tables(tables)
        return {name: table.column(name).to_numpy() for name in table.column_names}

    def dropped(self) -> dict[str, int]:
        """Rows not usable for training (``ok`` false) by reason (the status of the failed
        solve, e.g. ``"slack: infeasible"`` where (2.24) has no solution), SPEC §2.32."""
        cols = self.read(["ok", "reason"]) if self.completed() else {}
        if not cols or "reason" not in cols:
            return {}
        bad = ~np.asarray(cols["ok"], bool)
        return dict(Counter(str(r) for r in np.asarray(cols["reason"])[bad]))

    def throughput(self) -> dict[str, Any]:
        """Points, seconds and points per second per core over the runs recorded in the
        manifest (each call of :func:`run_sampling` that wrote shards adds one run)."""
        runs = self.manifest().get("runs", [])
        points = sum(r["points"] for r in runs)
        core_s = sum(r["seconds"] * r["workers"] for r in runs)
        wall = sum(r["seconds"] for r in runs)
        return {"runs": len(runs), "points": int(points), "wall_s": float(wall),
                "core_s": float(core_s),
                "points_per_s": float(points / wall) if wall > 0 else None,
                "points_per_core_s": float(points / core_s) if core_s > 0 else None}

    def arrays(self, target: str = "h", only_ok: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """``(X, y)`` for training: states (columns ``x0, x1, ...``) and the target column."""
        cols = self.read()
        if not cols:
            if not self.manifest_path.is_file():
                raise BalustradeError(f"{self.path}: no dataset there (no manifest.json; "
                                      f"'balustrade sample --out DIR' writes one)")
            raise BalustradeError(f"{self.path}: the dataset is empty")
        names = sorted((k for k in cols if k[0] == "x" and k[1:].isdigit()),
                       key=lambda k: int(k[1:]))
        X = np.column_stack([cols[k] for k in names])
        y = np.asarray(cols[target], dtype=float)
        keep = np.isfinite(y) & (cols["ok"] if only_ok and "ok" in cols else True)
        return X[keep], y[keep]


def run_sampling(path: str | Path, spec: ProblemSpec, chunks: Sequence[Chunk],
                 executor: Executor | None = None, config: dict[str, Any] | None = None,
                 progress: bool = True, stop_after: int | None = None) -> ShardedDataset:
    """Sample all ``chunks`` into the dataset at ``path``, skipping completed ones (resume).

    ``config`` (JSON-able) describes the plan; it is stored in the manifest and must match
    on resume. ``stop_after`` raises :class:`InterruptedRun` after that many shards were
    written in this call (fault injection for tests)."""
    ds = ShardedDataset(path)
    ids = [c.id for c in chunks]
    if len(set(ids)) != len(ids):
        raise BalustradeError("run_sampling: chunk ids must be unique")
    cfg = {"problem": spec.to_dict(), **(config or {}), "label_rule": LABEL_RULE}
    ds.init(json.loads(json.dumps(cfg, default=_jsonable)), len(chunks))
    done = ds.completed()
    todo = [c for c in chunks if c.id not in done]
    executor = executor or SerialExecutor()
    total = sum(len(c) for c in chunks)
    bar = Progress(total, desc=f"sampling {Path(path).name}", unit="points", enabled=progress,
                   initial=sum(len(c) for c in chunks if c.id in done))
    written, rows, start = 0, 0, time.perf_counter()
    workers = int(getattr(executor, "workers", 1) or 1)
    try:
        for chunk, columns in executor.imap_unordered(run_chunk, todo, spec):
            ds.write_shard(chunk.id, columns)
            workers = max(workers, int(getattr(executor, "workers", 1) or 1))  # a growing cluster
            written += 1
            rows += len(next(iter(columns.values()))) if columns else 0
            bar.update(len(chunk))
            if stop_after is not None and written >= stop_after:
                raise InterruptedRun(f"stopped after {written} chunks (stop_after)")
    finally:
        bar.close()
        if written:
            _record_run(ds, rows, written, time.perf_counter() - start, workers)
    return ds


def _record_run(ds: ShardedDataset, rows: int, chunks: int, seconds: float,
                workers: int) -> None:
    """Append this call's throughput (rows = sampled points incl. dropped ones) to the
    manifest: resumed runs add up in :meth:`ShardedDataset.throughput`."""
    manifest = ds.manifest()
    manifest.setdefault("runs", []).append(
        {"points": int(rows), "chunks": int(chunks), "seconds": float(seconds),
         "workers": int(workers),
         "points_per_core_s": float(rows / (seconds * workers)) if seconds > 0 else None})
    ds._write_manifest(manifest)


def _jsonable(obj: object) -> object:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    return str(obj)


def split_chunks(points: np.ndarray, chunk_size: int, kind: str = "grid", seed: int = 0,
                 first_id: int = 0, **options: Any) -> list[Chunk]:
    """Split ``points`` (rows, in order) into chunks of ``chunk_size`` with ids from
    ``first_id`` and seeds ``seed + id`` (deterministic)."""
    if chunk_size < 1:
        raise BalustradeError(f"split_chunks: chunk_size must be >= 1, got {chunk_size}")
    points = np.asarray(points, dtype=float)
    out = []
    for k, start in enumerate(range(0, len(points), chunk_size)):
        cid = first_id + k
        out.append(Chunk(cid, kind, points[start:start + chunk_size], seed=seed + cid,
                         **options))
    return out


def _grid_args(X: Any, lower: object, upper: object, steps: object
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``lower``, ``upper`` and ``steps`` of :func:`grid_plan`, checked against ``X.dim``."""
    n = int(X.dim)
    lo = as_vector(lower, f"grid_plan: lower (one entry per state of X, dim {n})", n)
    hi = as_vector(upper, f"grid_plan: upper (one entry per state of X, dim {n})", n)
    if np.any(hi < lo):
        bad = np.flatnonzero(hi < lo).tolist()
        raise BalustradeError(f"grid_plan: upper must be >= lower, got upper < lower at "
                              f"indices {bad} (lower {lo[bad]}, upper {hi[bad]})")
    where = f"grid_plan: grid step (one positive number, or one per state of X, dim {n})"
    st = as_float_array(steps, where)
    st = np.full(n, float(st.reshape(-1)[0])) if st.size == 1 else as_vector(st, where, n)
    if not np.all(np.isfinite(st)) or np.any(st <= 0):
        raise BalustradeError(f"{where}: must be finite and > 0, got {st}")
    return lo, hi, st.copy()


def grid_plan(X: Any, lower: object, upper: object, steps: object, chunk_size: int = 500,
              cap: float | None = 10.0, band: bool = True, warm: bool = True
              ) -> tuple[list[Chunk], dict[str, Any]]:
    """Section 7.5's data: a snake-ordered grid over ``[lower, upper]`` plus, if ``band``,
    points near the constraints (``0.8 b <= H_i x <= 1.2 b`` for a row of ``X``) on the grid
    shifted by half a step, all rejected above ``h_PB > cap``. Returns chunks and config.

    ``lower``, ``upper`` have one finite entry per state of ``X`` with ``lower <= upper``;
    ``steps`` is one positive step or one per state. Anything else raises a
    :class:`~balustrade.errors.BalustradeError` naming the argument and its shape (``balustrade
    sample --lower/--upper/--grid-step`` reach this function)."""
    lower, upper, steps_arr = _grid_args(X, lower, upper, steps)
    pts = snake_grid(lower, upper, steps_arr)
    chunks = split_chunks(pts, chunk_size, cap=cap, chain_distance=2.0 * float(steps_arr.max()),
                          warm=warm)
    n_band = 0
    if band:
        box_lo = np.maximum(np.asarray(lower, float), np.asarray(X.lb) * 1.2) + 0.5 * steps_arr
        box_hi = np.minimum(np.asarray(upper, float), np.asarray(X.ub) * 1.2)
        extra = band_points(X, box_lo, box_hi, steps_arr) if np.all(box_hi > box_lo) else []
        n_band = len(extra)
        if n_band:
            chunks += split_chunks(extra, chunk_size, first_id=len(chunks), cap=cap,
                                   chain_distance=2.0 * float(steps_arr.max()), warm=warm)
    config = {"mode": "grid", "lower": list(map(float, np.ravel(lower))),
              "upper": list(map(float, np.ravel(upper))), "steps": steps_arr.tolist(),
              "chunk_size": int(chunk_size), "cap": cap, "band": bool(band),
              "n_grid": int(len(pts)), "n_band": int(n_band), "warm": bool(warm)}
    return chunks, config


def geometric_plan(X: Any, n_goals: int, goals_per_chunk: int = 16, step: float = 0.01,
                   seed: int = 0, cap: float | None = None, scale: float = 1.5,
                   x_seed: Sequence[float] | None = None
                   ) -> tuple[list[Chunk], dict[str, Any]]:
    """Algorithm 7.6's work: ``n_goals`` scrambled Sobol goal points in ``scale ×`` the box of
    ``X``, split into chunks; each chunk walks lines from its own seed set (from ``x_seed``,
    default the origin), seeds drawn with ``default_rng(seed + chunk id)``. Independent
    training and validation sets (Section 8.3) use different ``seed`` (goals and seed
    draws) and ``x_seed``."""
    goals = sobol_goals(X, n_goals, seed=seed, scale=scale)
    xs = None if x_seed is None else tuple(float(v) for v in x_seed)
    if xs is not None and len(xs) != X.dim:
        raise BalustradeError(f"geometric_plan: x_seed must have {X.dim} entries, got "
                              f"{len(xs)}")
    chunks = split_chunks(goals, goals_per_chunk, kind="geometric", seed=seed, step=step,
                          cap=cap, x_seed=xs)
    config = {"mode": "geometric", "n_goals": int(n_goals), "goals_per_chunk":
              int(goals_per_chunk), "step": float(step), "seed": int(seed), "cap": cap,
              "scale": float(scale)}
    if xs is not None:
        config["x_seed"] = list(xs)
    return chunks, config
