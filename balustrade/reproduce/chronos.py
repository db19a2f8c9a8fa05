"""Section 8.4: the Chronos race car on the SPEC oval, with and without Algorithm 8.7.

Scenarios (SPEC §3.8), three laps each, simulated at 50 Hz on the Cartesian model (8.3)
(RK4, 10 sub-steps — no Frenet singularity when the car leaves the track); the controller
and the filter see the Frenet state ``[s, e, μ, v_x, v_y, ω]`` computed from the pose by
projection on the centre line (:meth:`~balustrade.models.track.Track.to_frenet`):

1. ``"p-controller"``: ``T = 0.3``, ``δ = clip(−K_p (e + ℓ sin μ), ±0.4)``, ``K_p = 1``.
   The SPEC default is ``ℓ = 0`` (pure lateral-error feedback); that loop is undamped
   (``ë ≈ −(v²K_p/l) e``) and spins off the track at the first curve, so the reproduction
   uses a look-ahead ``ℓ = 0.2`` m (design choice) which, like the thesis' controller, stays
   near the track but violates the constraints at curve entries; ``ℓ = 0`` is reported too.
2. ``"left"``: ``T = 0.3``, ``δ = +0.4``;  3. ``"right"``: ``T = 0.3``, ``δ = −0.4``.

A run stops after three laps of progress or at ``MAX_STEPS`` (the constant-steer cars
without filter circle and never finish a lap).

Filtered runs (Algorithm 8.7, :class:`~balustrade.control.approximate.GridPCBFFilter`,
grid ``ΔT = 0.1``, ``Δδ = 0.05``, rate limits ``0.5``/``0.1``, ``ρ = 0.9``) need a learned
``ĥ`` (4 × 32 softplus, :func:`train_h`) on data sampled with Algorithm 7.6 on the PCBF of
:mod:`balustrade.examples.chronos`. The full run samples at most ``SAMPLE_SHARDS`` chunks
per call into ``out/data`` (resumable: run again for more; the thesis used 1.6e8 points —
the cluster command is in ``docs/chronos.md``), trains and runs the three scenarios with
the filter; ``metrics.json`` says how many samples the network saw and whether the
constraints held (``all_within_tol``). The Python filter evaluates the network on all
candidates at once (:func:`h_rows`); with a C compiler the emitted C of Algorithm 8.7
(:func:`c_grid_filter`) runs scenario 1 too and ``metrics["c_filter"]`` says whether it
took the Python filter's inputs and statuses and how long both steps took
(:func:`compare_c`, interleaved). ``quick=True`` skips the learned part (reported as
not run). Measured in this session (docs/chronos.md): the SPEC §3.8 acceptance is not
met. With one fit on 2265 samples scenario 1 (and its noise/delay variants) stayed inside
for three laps and the constant-steer cars crossed the border at a few sites; a fit on
2703 samples failed in scenario 1; with 742 samples the filter failed everywhere. A
scaled-down sample is not the thesis' 1.6e8 points.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable
from pathlib import Path

import casadi as ca
import numpy as np

from balustrade.models.chronos import chronos_cartesian, constraint_values, steady_speed
from balustrade.models.track import Track, oval, plot_track
from balustrade.reproduce._plotting import figure, save

NAMES = ("chronos",)
LAPS = 3
MAX_STEPS = 1500
K_P, T_CMD, LOOKAHEAD = 1.0, 0.3, 0.2
#: Algorithm 8.7 settings of §8.4 (SPEC §2.34)
HALF_WIDTH, SPACING, RHO = (0.5, 0.1), (0.1, 0.05), 0.9
#: Algorithm 7.6 plan: goal points, chunks (of 4 goals) sampled per call, label cap
SAMPLE_GOALS, SAMPLE_SHARDS, CAP = 4096, 16, 5.0
#: std of the estimation noise on (e, μ) in the robustness variant
NOISE = 0.01
TOL = 1e-3

Controller = Callable[[np.ndarray], np.ndarray]


def p_controller(k_p: float = K_P, T: float = T_CMD, lookahead: float = LOOKAHEAD
                 ) -> Controller:
    """Scenario 1: ``u = (T, clip(−K_p (e + ℓ sin μ), ±0.4))`` on the Frenet state."""
    def u(x: np.ndarray) -> np.ndarray:
        return np.array([T, float(np.clip(-k_p * (x[1] + lookahead * np.sin(x[2])), -0.4,
                                          0.4))])
    return u


def constant(T: float = T_CMD, delta: float = 0.4) -> Controller:
    """Scenarios 2 and 3: constant drive and steer."""
    def u(x: np.ndarray) -> np.ndarray:
        return np.array([T, delta])
    return u


SCENARIOS: dict[str, Controller] = {
    "p-controller": p_controller(),
    "left": constant(delta=0.4),
    "right": constant(delta=-0.4),
}


def closed_loop(track: Track, controller: Controller, safety_filter: object = None,
                laps: int = LAPS, max_steps: int = MAX_STEPS, v0: float = 0.5,
                noise: float = 0.0, delay: bool = False, seed: int = 0) -> dict[str, np.ndarray]:
    """Simulate from the start of the track (on the centre line, speed ``v0``) until
    ``laps`` laps of progress or ``max_steps``. ``noise``: std of Gaussian estimation noise
    on ``(e, μ)`` (m, rad) and ``0.05·noise`` on the velocities seen by controller and
    filter; ``delay``: the input computed at step ``k`` is applied at ``k + 1``."""
    rng = np.random.default_rng(seed)
    plant = chronos_cartesian()
    px, py, psi = track.to_cartesian(0.0, 0.0, 0.0)
    xc = np.array([float(px), float(py), float(psi), v0, 0.0, 0.0])
    cart, fren, U_p, U, times, status = [], [], [], [], [], []
    progress, s_prev = 0.0, 0.0
    pending = np.array([0.0, 0.0])
    for _ in range(max_steps):
        s, e, mu = (float(v[0]) for v in track.to_frenet(xc[0], xc[1], xc[2]))
        xf = np.array([s, e, mu, *xc[3:]])
        progress += (s - s_prev + track.length / 2) % track.length - track.length / 2
        s_prev = s
        cart.append(xc.copy())
        fren.append(xf)
        if progress >= laps * track.length:
            break
        seen = xf.copy()
        if noise > 0:
            seen[1:3] += noise * rng.standard_normal(2)
            seen[3:] += 0.05 * noise * rng.standard_normal(3)
        u_p = controller(seen)
        if safety_filter is not None:
            t0 = time.perf_counter()
            u, info = safety_filter.step(seen, u_p)
            times.append(time.perf_counter() - t0)
            status.append(info.status)
        else:
            u = u_p
        U_p.append(u_p)
        U.append(u)
        applied = pending if delay else u
        pending = np.asarray(u, dtype=float)
        xc = plant.step(xc, applied)
    fren_arr = np.array(fren)
    return {"cartesian": np.array(cart), "frenet": fren_arr,
            "c_max": constraint_values(fren_arr).max(axis=1),
            "u_p": np.array(U_p).reshape(-1, 2), "u": np.array(U).reshape(-1, 2),
            "laps": np.array(progress / track.length), "times": np.array(times),
            "status": np.array(status)}


def violation_sites(run: dict[str, np.ndarray], tol: float = 0.0) -> list[dict[str, float]]:
    """Contiguous stretches with ``max c_x > tol``: where they start (``s``, ``x``, ``y``),
    their length in steps and the largest violation (m or rad)."""
    bad = run["c_max"] > tol
    sites = []
    k = 0
    while k < bad.size:
        if not bad[k]:
            k += 1
            continue
        j = k
        while j < bad.size and bad[j]:
            j += 1
        sites.append({"s": float(run["frenet"][k, 0]), "x": float(run["cartesian"][k, 0]),
                      "y": float(run["cartesian"][k, 1]), "steps": int(j - k),
                      "max_violation": float(run["c_max"][k:j].max())})
        k = j
    return sites


def _summary(run: dict[str, np.ndarray]) -> dict:
    sites = violation_sites(run)
    out = {"steps": int(run["frenet"].shape[0]), "laps": float(run["laps"]),
           "max_constraint": float(run["c_max"].max()), "violation_sites": len(sites),
           "sites": sites[:20],
           # the acceptance of §3.8: constraints within TOL *for three laps* (a car that
           # stalls before the third lap does not pass)
           "completed_laps": bool(float(run["laps"]) >= LAPS - 1e-9),
           "within_tol": bool(run["c_max"].max() <= TOL and float(run["laps"]) >= LAPS - 1e-9),
           "max_abs_mu": float(np.max(np.abs(run["frenet"][:, 2])))}
    if run["times"].size:
        out["filter_time_median_ms"] = float(1e3 * np.median(run["times"]))
        out["filter_time_max_ms"] = float(1e3 * np.max(run["times"]))
        out["intervention_mean"] = float(np.mean(np.abs(run["u"] - run["u_p"]).sum(axis=1)))
        vals, counts = np.unique(run["status"], return_counts=True)
        out["statuses"] = {str(v): int(c) for v, c in zip(vals, counts)}
    return out


def _plot_runs(out: Path, track: Track, runs: dict[str, dict], title: str, fname: str) -> str:
    fig, axes = figure(1, len(runs), size=(5.0 * len(runs), 4.2))
    axes = np.atleast_1d(axes)
    for ax, (name, run) in zip(axes, runs.items()):
        sites = violation_sites(run)
        marks = np.array([[s["x"], s["y"]] for s in sites]) if sites else None
        color = (np.r_[np.abs(run["u"] - run["u_p"]).sum(axis=1), 0.0]
                 if run["times"].size else None)
        lc = plot_track(ax, track, [run["cartesian"][:, :2]],
                        color_by=None if color is None else [color[: len(run["cartesian"])]],
                        markers=marks)
        if lc is not None:
            fig.colorbar(lc, ax=ax, shrink=0.6, label="|u - u_p|_1")
        ax.set_title(f"{name}: {len(sites)} violation sites")
    fig.suptitle(title)
    return save(fig, out / fname)


def _plot_inputs(out: Path, runs: dict[str, dict], fname: str) -> str:
    fig, axes = figure(2, len(runs), size=(5.0 * len(runs), 5.0))
    axes = np.asarray(axes).reshape(2, -1)
    for j, (name, run) in enumerate(runs.items()):
        t = 0.02 * np.arange(len(run["u"]))
        for i, label in enumerate(("T", "delta")):
            axes[i, j].plot(t, run["u_p"][:, i], "--", color="0.5", label="u_p")
            axes[i, j].plot(t, run["u"][:, i], lw=1.0, label="u")
            axes[i, j].set_ylabel(label)
        axes[0, j].set_title(name)
        axes[1, j].set_xlabel("t (s)")
        axes[0, j].legend(fontsize=7)
    return save(fig, out / fname)


# -- the learned filter --------------------------------------------------------------------------
def _sample(out: Path, n_goals: int, shards: int | None) -> object:
    """Algorithm 7.6 on the §8.4 PCBF: Sobol goal points in the design's sampling box, lines
    of step 0.1 from seeds that start on the centre line at 1 m/s, walks stopped above
    ``h_PB > 5``; at most ``shards`` chunks of 4 goals in this call (the data set resumes:
    run again for more)."""
    from balustrade.learn.dataset import (
        InterruptedRun,
        ShardedDataset,
        geometric_plan,
        run_sampling,
    )
    from balustrade.learn.executors import make_executor
    from balustrade.learn.sampler import ProblemSpec

    spec = ProblemSpec.of("chronos", target="exact")
    X = spec.build().X
    chunks, plan = geometric_plan(X, n_goals, goals_per_chunk=4, step=0.1, seed=0, cap=CAP,
                                  scale=1.0)
    seed = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0)
    chunks = [dataclasses.replace(c, x_seed=seed) for c in chunks]
    plan["x_seed"] = list(seed)
    try:
        with make_executor(1) as ex:
            return run_sampling(out, spec, chunks, ex, plan, progress=False,
                                stop_after=shards)
    except InterruptedRun:
        return ShardedDataset(out)


def train_h(X: np.ndarray, y: np.ndarray, epochs: int = 300, seed: int = 0) -> object:
    """The 4 × 32 softplus network of §8.4 (lr 1e-3, batch 64, 5 % validation) on the
    samples with ``h <= CAP``, fitted to ``∛h`` (``ĥ = net³``, the label transform of
    Section 8.3) with a cosine learning-rate schedule. ``epochs`` replaces the thesis' 10:
    on a few hundred points 10 epochs are a few dozen optimizer steps (measured: validation
    MSE 0.10 with the plain fit on 742 points, 9e-4 with this one)."""
    from balustrade.learn.train import TrainConfig, train

    keep = np.isfinite(y) & (y <= CAP)
    cfg = TrainConfig(widths=(32, 32, 32, 32), epochs=epochs, lr=1e-3, batch_size=64,
                      val_fraction=0.05, seed=seed, output_transform="cbrt",
                      lr_schedule="cosine")
    return train(X[keep], y[keep], cfg)


def h_function(model: object, track: Track) -> ca.Function:
    """``ĥ`` as a CasADi Function of the Frenet state with ``s`` wrapped into ``[0, L)``
    (the network saw ``s`` in one lap only)."""
    from balustrade.learn.export import expression

    x = ca.SX.sym("x", 6)
    L = track.length
    xw = ca.vertcat(x[0] - L * ca.floor(x[0] / L), x[1:])
    return ca.Function("h_hat", [x], [expression(model, xw)])


def h_rows(model: object, track: Track) -> Callable[[np.ndarray], np.ndarray]:
    """The ``ĥ`` of :func:`h_function` on the rows of an ``(M, 6)`` array, evaluated by the
    network's numpy forward pass (dense matrix products; the ``h_rows`` of
    :class:`~balustrade.control.approximate.GridPCBFFilter`), ``s`` wrapped as there."""
    L = track.length

    def rows(X: np.ndarray) -> np.ndarray:
        X = np.array(X, dtype=float, ndmin=2)
        X[:, 0] = X[:, 0] - L * np.floor(X[:, 0] / L)
        return model(X)
    return rows


def grid_filter(h_hat: ca.Function, track: Track,
                rows: Callable[[np.ndarray], np.ndarray] | None = None) -> object:
    """Algorithm 8.7 on the Euler Frenet model with the §8.4 grid and ``ρ = 0.9``;
    ``rows`` (e.g. :func:`h_rows`) evaluates ``ĥ`` on all candidates at once."""
    from balustrade.control.approximate import GridPCBFFilter
    from balustrade.models.chronos import chronos_frenet, chronos_sets

    _, U = chronos_sets()
    return GridPCBFFilter(chronos_frenet(track), U, h_hat, HALF_WIDTH, SPACING, rho=RHO,
                          u_init=np.array([T_CMD, 0.0]), h_rows=rows)


def c_grid_filter(py_filter: object, build_dir: str | Path | None = None) -> object:
    """The emitted C of Algorithm 8.7 (:func:`~balustrade.codegen.emit_grid.emit_grid`:
    ``ĥ`` and the Frenet model with the track's ``κ(s)``, one call per step) built and
    loaded as a controller (:func:`~balustrade.codegen.accelerate`), reset."""
    from balustrade.codegen import accelerate

    return accelerate(py_filter, build_dir=build_dir, name="chronos_grid", werror=True)


def compare_c(py_filter: object, c_filter: object, states: np.ndarray,
              proposals: np.ndarray) -> dict:
    """Both filters (reset) stepped in lockstep on the same ``states`` and proposals,
    interleaved (Python, C, Python, C …) so both see the same load: the largest input
    difference, whether every status agreed, and the per-step wall times (median, ms)."""
    py_filter.reset()
    c_filter.reset()
    t_py, t_c, t_native, du, same = [], [], [], 0.0, True
    for x, u_p in zip(states, proposals):
        t0 = time.perf_counter()
        u1, i1 = py_filter.step(x, u_p)
        t1 = time.perf_counter()
        u2, i2 = c_filter.step(x, u_p)
        t2 = time.perf_counter()
        t_py.append(t1 - t0)
        t_c.append(t2 - t1)
        t_native.append(i2.solve_time)  # the foreign call alone
        du = max(du, float(np.max(np.abs(np.asarray(u1) - np.asarray(u2)))))
        same = same and (i1.status, i1.fallback) == (i2.status, i2.fallback)
    return {"steps": len(t_py), "max_input_difference": du, "statuses_equal": bool(same),
            "python_step_median_ms": float(1e3 * np.median(t_py)),
            "c_step_median_ms": float(1e3 * np.median(t_c)),
            "c_call_median_ms": float(1e3 * np.median(t_native)),
            "python_step_max_ms": float(1e3 * np.max(t_py)),
            "c_step_max_ms": float(1e3 * np.max(t_c))}


def _filtered(out: Path, track: Track, metrics: dict) -> dict[str, dict]:
    t0 = time.time()
    ds = _sample(out / "data", SAMPLE_GOALS, SAMPLE_SHARDS)
    X, y = ds.arrays("h")
    metrics["sampling"] = {"points": int(len(y)), "seconds": time.time() - t0,
                           "thesis_points": 1.6e8, "in_S_PB": int(np.sum(y <= 0)),
                           "shards_per_call": SAMPLE_SHARDS}
    model = train_h(X, y)
    model.save(out / "h_hat.npz")
    val = model.history.get("val_mse_h", [])
    metrics["training"] = {"widths": [32] * 4, "epochs": 300, "lr": 1e-3, "batch_size": 64,
                           "transform": "cbrt", "val_mse": float(val[-1]) if val else None}
    h_hat, rows = h_function(model, track), h_rows(model, track)
    runs = {name: closed_loop(track, ctrl, grid_filter(h_hat, track, rows))
            for name, ctrl in SCENARIOS.items()}
    # robustness variants of scenario 1: estimation noise (1 cm, 0.01 rad) and a one-step
    # input delay
    ctrl = SCENARIOS["p-controller"]
    runs["p-controller+noise"] = closed_loop(track, ctrl, grid_filter(h_hat, track, rows),
                                             noise=NOISE)
    runs["p-controller+delay"] = closed_loop(track, ctrl, grid_filter(h_hat, track, rows),
                                             delay=True)
    try:
        metrics["c_filter"] = _c_filter(out, track, grid_filter(h_hat, track, rows),
                                        runs["p-controller"])
    except Exception as exc:  # noqa: BLE001 - reported, never faked
        metrics["c_filter"] = {"status": "failed", "reason": f"{type(exc).__name__}: {exc}"}
    return runs


def _c_filter(out: Path, track: Track, py_filter: object, run_py: dict) -> dict:
    """The emitted C of Algorithm 8.7 on scenario 1: the closed loop with the C filter
    against the Python one (inputs, states, statuses) and both steps timed interleaved on
    the states of the Python run. Reported as not run when there is no C compiler."""
    from balustrade.codegen import find_compiler
    from balustrade.errors import CodegenError

    try:
        find_compiler()
    except CodegenError as exc:
        return {"status": f"not run: {exc}"}
    t0 = time.time()
    c = c_grid_filter(py_filter, out / "c")
    build_s = time.time() - t0
    # the same step budget: both runs stop at three laps or where the Python run stopped
    run_c = closed_loop(track, SCENARIOS["p-controller"], c,
                        max_steps=len(run_py["frenet"]))
    n = min(len(run_c["u"]), len(run_py["u"]))
    m = min(len(run_c["frenet"]), len(run_py["frenet"]))
    loop = {"steps": int(n), "same_length": len(run_c["u"]) == len(run_py["u"]),
            "max_input_difference": float(np.max(np.abs(run_c["u"][:n] - run_py["u"][:n]))),
            "max_state_difference": float(np.max(np.abs(run_c["frenet"][:m] -
                                                        run_py["frenet"][:m]))),
            "statuses_equal": bool(np.array_equal(run_c["status"], run_py["status"]))}
    timing = compare_c(py_filter, c, run_py["frenet"][: len(run_py["u_p"])], run_py["u_p"])
    return {"status": "built", "dir": str(c.accelerated["dir"]), "build_s": build_s,
            "closed_loop_p_controller": loop, "replay_p_controller": timing,
            "c_equals_python": bool(loop["same_length"] and loop["statuses_equal"] and
                                    loop["max_input_difference"] <= 1e-6 and
                                    timing["statuses_equal"] and
                                    timing["max_input_difference"] <= 1e-6),
            "load": "2 cores shared with other jobs: times are under load"}


def run(out: Path, quick: bool = False) -> dict:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    track = oval()
    metrics: dict = {"track": {**track.closure(), "length": track.length,
                               "closed": track.is_closed()},
                     "steady_speed_T0.3": steady_speed(T_CMD)}
    max_steps = 200 if quick else MAX_STEPS
    plain = {name: closed_loop(track, ctrl, max_steps=max_steps)
             for name, ctrl in SCENARIOS.items()}
    metrics["unfiltered"] = {name: _summary(r) for name, r in plain.items()}
    no_look = closed_loop(track, p_controller(lookahead=0.0), max_steps=max_steps)
    metrics["unfiltered_p_controller_lookahead_0"] = _summary(no_look)
    from balustrade.examples.chronos import check_invariance, chronos_design, time_pcbf

    design = chronos_design(track=track)
    t0 = time.time()
    inv = check_invariance(design.cbf, design.system, starts=2 if quick else 50)
    metrics["terminal_cbf"] = {"P": design.cbf.P.tolist(), "K": design.cbf.K.tolist(),
                               "invariance_check": dataclasses.asdict(inv),
                               "no_counterexample": inv.ok, "seconds": time.time() - t0}
    metrics["pcbf_solve"] = time_pcbf(("exact",) if quick else
                                      ("exact", "fast-sqp", "structured-sqp", "long-horizon"),
                                      n_states=1 if quick else 5, design=design)
    figures = [_plot_runs(out, track, plain, "without the filter", "chronos_unfiltered.png"),
               _plot_inputs(out, plain, "chronos_unfiltered_inputs.png")]
    if quick:
        metrics["filtered"] = {"status": "not run (quick): sampling the PCBF at N = 50 takes "
                                         "about a second per point"}
        metrics["c_filter"] = {"status": "not run (quick): the C filter needs the learned ĥ"}
        metrics["figures"] = figures
        (out / "metrics.json").write_text(json.dumps(metrics, indent=2, default=float))
        return metrics
    try:
        runs = _filtered(out, track, metrics)
    except Exception as exc:  # noqa: BLE001 - reported, never faked
        metrics["filtered"] = {"status": "not built", "reason": f"{type(exc).__name__}: {exc}"}
    else:
        summary = {name: _summary(r) for name, r in runs.items()}
        metrics["filtered"] = {"status": "built",
                               "scenarios": summary,
                               "all_within_tol": all(s["within_tol"] for s in
                                                     summary.values())}
        main = {k: runs[k] for k in SCENARIOS}
        figures += [_plot_runs(out, track, main, "with Algorithm 8.7", "chronos_filtered.png"),
                    _plot_inputs(out, main, "chronos_filtered_inputs.png")]
    metrics["figures"] = figures
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2, default=float))
    return metrics


__all__ = ["NAMES", "SCENARIOS", "c_grid_filter", "closed_loop", "compare_c", "constant",
           "grid_filter", "h_function", "h_rows", "p_controller", "run", "violation_sites"]
