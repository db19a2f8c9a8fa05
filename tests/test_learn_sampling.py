"""Sampling the extended PCBF (Algorithm 7.6, SPEC §2.30) at scale: warm starts, executors
(local processes, Dask), resumable sharded datasets."""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from balustrade.backends import compile
from balustrade.errors import BalustradeError
from balustrade.learn.dataset import InterruptedRun, ShardedDataset, run_sampling, split_chunks
from balustrade.learn.executors import DaskExecutor, LocalExecutor, SerialExecutor
from balustrade.learn.progress import Progress
from balustrade.learn.sampler import (
    Chunk,
    Evaluator,
    PCBFProblems,
    ProblemSpec,
    Seed,
    band_points,
    run_chunk,
    snake_grid,
    sobol_goals,
)

SPEC = ProblemSpec.of("pendulum")


@pytest.fixture(scope="module")
def problems() -> PCBFProblems:
    return SPEC.build()


@pytest.fixture(scope="module")
def plan() -> list[Chunk]:
    pts = snake_grid([-1.0, -3.0], [1.0, 3.0], [0.2, 0.5])
    return split_chunks(pts, 20, cap=10.0)


@pytest.fixture(scope="module")
def reference(plan, tmp_path_factory) -> dict[str, np.ndarray]:
    ds = run_sampling(tmp_path_factory.mktemp("ref"), SPEC, plan, SerialExecutor(),
                      progress=False)
    assert ds.done
    return ds.read()


def same(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> bool:
    return a.keys() == b.keys() and all(  # equal_nan only for numbers (not the reason text)
        np.array_equal(a[k], b[k], equal_nan=a[k].dtype.kind in "fc") for k in a)


def test_warm_started_line_walk_agrees_with_cold_solves(problems):
    """Warm starts (previous primal AND dual) change the work, not the values."""
    warm, cold = Evaluator(problems, warm=True), Evaluator(problems, warm=False)
    x0, goal = np.array([0.0, 0.0]), np.array([0.9, 2.4])
    line_w, _ = warm.walk(x0, goal, 0.02, Seed(x0))
    line_c, _ = cold.walk(x0, goal, 0.02, Seed(x0))
    assert len(line_w) == len(line_c) == int(np.ceil(np.linalg.norm(goal - x0) / 0.02))
    hw, hc = np.array([s.h for s in line_w]), np.array([s.h for s in line_c])
    assert np.all([s.ok for s in line_w + line_c])
    assert np.max(np.abs(hw - hc) / np.maximum(1.0, np.abs(hc))) < 1e-5
    assert [s.in_s for s in line_w] == [s.in_s for s in line_c]
    # the line crosses ∂S_PB, so both problems and the switching were exercised
    assert line_w[0].in_s and not line_w[-1].in_s
    # warm starts save iterations (warm sqpmethod ≈ 1 SQP iteration vs cold IPOPT)
    assert sum(s.iterations for s in line_w) < 0.7 * sum(s.iterations for s in line_c)
    # against the convex reference solver (Clarabel through cvxpy) at a few points
    ref = PCBFProblems(compile(problems.slack.ocp, "cvxpy"),
                       compile(problems.extended.ocp, "cvxpy"), problems.X)
    for s in line_w[::25]:
        r, _ = Evaluator(ref, warm=False).point(s.x, Seed(s.x))
        assert s.h == pytest.approx(r.h, rel=1e-5, abs=1e-5)


@pytest.fixture(scope="module")
def clarabel(problems) -> PCBFProblems:
    """(2.24) and (7.8) on the cvxpy backend (Clarabel: an independent conic solver)."""
    return PCBFProblems(compile(problems.slack.ocp, "cvxpy"),
                        compile(problems.extended.ocp, "cvxpy"), problems.X)


@pytest.mark.parametrize(("target", "solver"), [("fast-sqp", "sqpmethod"), ("exact", "ipopt")])
def test_sampled_values_agree_with_clarabel_on_a_test_grid(problems, clarabel, target, solver):
    """Warm-started sampling (``sqpmethod`` warm + IPOPT cold, the default, or IPOPT
    only) against Clarabel at every point: a coarse snake grid over 1.25 × X (points far
    outside S_PB, h up to ~1e8) and a fine line walk through ∂S_PB."""
    probs = problems if target == "fast-sqp" else ProblemSpec.of("pendulum",
                                                                  target=target).build()
    assert probs.slack.solver_name == solver
    ev = Evaluator(probs, warm=True)
    grid = ev.path(snake_grid([-2.5, -10.0], [2.5, 10.0], [0.5, 2.0]))
    x0 = np.zeros(2)
    line, _ = ev.walk(x0, np.array([0.9, 2.4]), 0.02, Seed(x0))
    ref = Evaluator(clarabel, warm=False)
    n_in = 0
    for s in grid + line:
        r, _ = ref.point(s.x, Seed(s.x))
        assert s.ok and r.ok
        assert abs(s.h - r.h) <= 1e-6 * max(1.0, abs(r.h)), (s.x, s.h, r.h)
        if abs(r.h) > 1e-5:
            assert s.in_s == r.in_s
        n_in += s.in_s
    assert 0 < n_in < len(grid) + len(line)


def test_algorithm_7_6_values_are_consistent(problems):
    goals = sobol_goals(problems.X, 6, seed=2)
    lo, hi = -0.75 * (problems.X.ub - problems.X.lb), 0.75 * (problems.X.ub - problems.X.lb)
    assert np.all(goals >= lo) and np.all(goals <= hi)
    cols = run_chunk(SPEC, Chunk(0, "geometric", goals, seed=4, step=0.05))
    assert np.all(cols["ok"])
    h, h_pb, in_s = cols["h"], cols["h_pb"], cols["in_s"]
    assert np.array_equal(in_s, h <= 0)                         # h <= 0 ⟺ x ∈ S_PB
    np.testing.assert_allclose(h_pb, np.maximum(0.0, h))        # max{0, h} = h_PB
    assert in_s.any() and (~in_s).any()
    X = np.column_stack([cols["x0"], cols["x1"]])
    c = X @ problems.X.H.T - problems.X.h
    assert np.all(h[in_s] >= c.max(axis=1)[in_s] - 1e-6)       # h̄ >= max_j c_x,j(x)
    steps = np.linalg.norm(np.diff(X, axis=0), axis=1)
    assert np.median(steps) <= 0.05 + 1e-12                     # points on lines of step d


def test_grid_rejection_and_band_points(problems):
    band = band_points(problems.X, [-0.7, -2.0], [0.7, 2.0], 0.05)
    Hx = band @ problems.X.H.T
    assert np.all(np.any((Hx >= 0.8 * problems.X.h) & (Hx <= 1.2 * problems.X.h), axis=1))
    pts = snake_grid([-2.0, -8.0], [2.0, 8.0], [1.0, 4.0])
    assert len(pts) == 25 and np.all(np.linalg.norm(np.diff(pts, axis=0), axis=1) <= 4.0)
    cols = run_chunk(SPEC, Chunk(0, "grid", pts, cap=10.0))
    assert 0 < len(cols["h"]) < 25 and np.all(cols["h_pb"] <= 10.0)


def test_resume_after_injected_failure_gives_the_same_dataset(plan, reference, tmp_path):
    with pytest.raises(InterruptedRun):
        run_sampling(tmp_path, SPEC, plan, SerialExecutor(), progress=False, stop_after=3)
    ds = ShardedDataset(tmp_path)
    assert sorted(ds.completed()) == [c.id for c in plan[:3]] and not ds.done
    # a crash between a shard write and the manifest update leaves an orphan shard
    ds.shard_path(plan[5].id).write_bytes(b"half-written garbage")
    with pytest.raises(InterruptedRun):
        run_sampling(tmp_path, SPEC, plan, SerialExecutor(), progress=False, stop_after=1)
    run_sampling(tmp_path, SPEC, plan, SerialExecutor(), progress=False)
    got = ds.read()
    assert ds.done and same(got, reference)
    keys = set(zip(got["chunk"].tolist(), got["index"].tolist()))
    assert len(keys) == len(got["h"])                            # no duplicates
    assert len({(a, b) for a, b in zip(got["x0"], got["x1"])}) == len(got["h"])
    assert not list(tmp_path.glob(".*tmp*"))
    with pytest.raises(BalustradeError):                         # a different plan is refused
        run_sampling(tmp_path, SPEC, plan[:-1], SerialExecutor(), progress=False)


def test_dataset_of_an_older_label_rule_refuses_to_resume(plan, tmp_path):
    """A dataset sampled before the slack-guess retry (no ``label_rule`` in its manifest)
    must not be resumed: its labels and the new ones would mix (audit D, session 15)."""
    with pytest.raises(InterruptedRun):
        run_sampling(tmp_path, SPEC, plan, SerialExecutor(), progress=False, stop_after=1)
    ds = ShardedDataset(tmp_path)
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    assert manifest["config"]["label_rule"] == 3
    del manifest["config"]["label_rule"]
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(BalustradeError, match="label_rule: 'none' vs 3"):
        run_sampling(tmp_path, SPEC, plan, SerialExecutor(), progress=False)
    assert len(ds.completed()) == 1                              # nothing lost


def test_local_processes_and_dask_equal_serial(plan, reference, tmp_path):
    from distributed import Client, LocalCluster

    with LocalExecutor(2) as ex:
        local = run_sampling(tmp_path / "local", SPEC, plan, ex, progress=False).read()
    assert same(local, reference)
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster:
        with DaskExecutor(cluster.scheduler_address) as ex:   # as a user passes an address
            dask = run_sampling(tmp_path / "dask", SPEC, plan, ex, progress=False).read()
        with Client(cluster) as client:                       # or an existing client
            half = run_sampling(tmp_path / "dask2", SPEC, plan[:3],
                                DaskExecutor(client=client), progress=False).read()
    assert same(dask, reference)
    assert np.array_equal(half["h"], reference["h"][: len(half["h"])], equal_nan=True)


def test_dask_counts_worker_threads_not_workers():
    """Throughput per core divides by the cores the cluster has: the threads of all workers
    (a worker with 2 threads is 2 cores), not the number of workers at connect time."""
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=2, processes=False,
                      dashboard_address=None) as cluster, Client(cluster) as client:
        assert DaskExecutor(client=client).workers == 2


def test_killed_subprocess_resumes_to_the_same_dataset(tmp_path):
    out = tmp_path / "killed"
    args = [sys.executable, "-m", "balustrade.cli", "sample", "--out", str(out),
            "--lower", "-1", "-3", "--upper", "1", "3", "--grid-step", "0.08", "0.25",
            "--chunk-size", "25", "--workers", "1", "--cap", "10", "--no-band", "--quiet"]
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    ds = ShardedDataset(out)
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None:
        if ds.manifest_path.exists() and len(ds.completed()) >= 3:
            break
        time.sleep(0.02)
    assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    n_chunks = ds.manifest()["n_chunks"]
    assert 3 <= len(ds.completed()) < n_chunks
    subprocess.run(args, check=True, capture_output=True)
    again = tmp_path / "fresh"
    fresh_args = args.copy()
    fresh_args[fresh_args.index(str(out))] = str(again)
    subprocess.run(fresh_args, check=True, capture_output=True)
    assert ds.done and same(ds.read(), ShardedDataset(again).read())


def test_progress_bar_reports_rate_and_eta():
    buf = io.StringIO()
    bar = Progress(100, desc="demo", unit="pts", stream=buf, log_interval=0.0)
    bar.update(10)
    time.sleep(0.01)
    bar.update(15)
    bar.close()
    lines = buf.getvalue().strip().splitlines()
    assert lines[-1].startswith("demo: 25/100 pts [ 25.0%]")
    assert "pts/s" in lines[-1] and "ETA" in lines[-1]
    assert json.loads(json.dumps(bar.rate)) > 0


def test_cli_geometric_mode_from_a_config_file(tmp_path):
    from balustrade.cli import main

    cfg = tmp_path / "sample.json"
    cfg.write_text(json.dumps({"mode": "geometric", "goals": 4, "goals_per_chunk": 2,
                               "line_step": 0.1, "seed": 5, "workers": 1, "quiet": True}))
    out = tmp_path / "geo"
    assert main(["sample", "--config", str(cfg), "--out", str(out)]) == 0
    ds = ShardedDataset(out)
    assert ds.done and ds.manifest()["config"]["mode"] == "geometric"
    cols = ds.read()
    assert sorted(set(cols["chunk"].tolist())) == [0, 1] and np.all(cols["ok"])
    assert np.array_equal(cols["in_s"], cols["h"] <= 0)
    cfg.write_text(json.dumps({"no_such_option": 1}))
    assert main(["sample", "--config", str(cfg), "--out", str(out)]) == 2


def test_cli_config_with_the_old_solver_key_says_it_was_renamed(tmp_path, capsys):
    """A sample config written before targets ("solver": "sqpmethod") is refused with the new
    key's name, not only "unknown keys"."""
    from balustrade.cli import main

    cfg = tmp_path / "old.json"
    cfg.write_text(json.dumps({"solver": "sqpmethod"}))
    assert main(["sample", "--config", str(cfg), "--out", str(tmp_path / "o")]) == 2
    assert "'solver' is now 'target'" in capsys.readouterr().err


class _FailingExtended:
    """(7.8) that never converges but leaves a finite objective (its last iterate)."""

    def __init__(self, inner) -> None:
        self.inner = inner

    def solve(self, params, warm_start=None, **kw):
        sol = self.inner.solve(params)
        sol.status, sol.objective = "failed", -0.25
        return sol


def test_failed_extended_solve_gives_no_label(problems: PCBFProblems) -> None:
    """On ``S_PB`` the label is ``c_h·h̄_PB`` from a converged (7.8) only. When (7.8) fails
    (warm and cold) and (2.24) then places ``x`` in ``S_PB``, the failed solve's objective
    was used as the label of a good row (audit B, session 14); the row is dropped now."""
    import dataclasses

    x = np.zeros(problems.nx)                     # the origin: inside S_PB
    good, _ = Evaluator(problems, warm=False).point(x, Seed(x, in_s=True))
    assert good.ok and good.in_s and good.h < 0   # the independent value h̄_PB(0) < 0
    broken = dataclasses.replace(problems, extended=_FailingExtended(problems.extended),
                                 extended_cold=_FailingExtended(problems.extended))
    s, _ = Evaluator(broken, warm=False).point(x, Seed(x, in_s=True))
    assert s.in_s and s.h_pb == 0.0               # (2.24) converged: x ∈ S_PB
    assert not s.ok and np.isnan(s.h), (s.ok, s.h)
    assert "extended" in s.reason
