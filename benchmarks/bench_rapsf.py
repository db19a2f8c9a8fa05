"""Per-step time of Algorithm 4.1 (the robust adaptive predictive safety filter, thesis
Chapter 4, SPEC §2.21) on the mass–spring–damper chain of §4.7 (SPEC §3.2), the parameter-set
update included (the box update :class:`~balustrade.estimate.BoxUpdate`: ``2q`` LPs in one
HiGHS run on the ``update_lp_steps`` steps whose transition cuts ``Θ_{k−1}``, none on the
others, where ``Θ_{k−1} ⊆ Δ_k``; and the constants ``s_jr`` of a new ``Θ_k``).

Paths, timed interleaved on the same states in one run (blocks of 10 steps, path after path,
:func:`benchmarks._timing.interleaved`), each one ``controller.step`` per state:

* ``default`` — ``RAPSF(...)`` without ``target=`` (:data:`~balustrade.control.rapsf.
  DEFAULT_TARGET`, ``"fast-convex-sized"``: DAQP hot-started on 3 masses, row generation on
  PIQP on 8; the row's ``engine`` says which solver ran);
* ``fast-convex`` — :class:`~balustrade.control.rapsf.RAPSF` with the ``Θ_k``-vertex data as
  parameters: (4.5) compiled once, the direct backend updates the values of the constraint
  matrix ``A(p)`` per step;
* ``fast-convex every row`` — the same with every row of (4.5c) written per vertex, as
  before the exact row reductions of :func:`~balustrade.problems.rapsf.rapsf_problem`
  (``shared``, ``factored``; :func:`every_row`);
* ``fast-convex constants`` — the same with ``vertex_data="constants"``: (4.5) recompiled
  whenever ``Θ_k`` changes (the form before issue #15 item 1 on the convex targets);
* ``exact`` — CasADi + IPOPT with the vertex data as parameters;
* ``cvxpy rebuilt every step`` — the baseline the issue names: the same update, then (4.5)
  written in plain cvxpy from the current vertices and solved (PIQP, the tolerances of
  balustrade's cvxpy target), rebuilt from scratch every step (the thesis' YALMIP way).

``ratio`` is the baseline's median over the path's; ``mean_s``/``max_s`` show what the median
hides (the recompiles of the constant form happen only on the ``theta_changes`` steps where
``Θ_k`` changed). ``fast-convex-conic`` is the direct backend on Clarabel instead of PIQP.
Every path runs its own closed loop (:class:`Loop`) with the same ``θ*`` (uniform in ``Θ₀``)
and disturbance sequence (seed 0) and the aggressive
:func:`~balustrade.models.msd.msd_performance`, so a path whose solve fails continues with its
own fallback (``fallbacks``: steps that did not apply a fresh optimal solve) and its estimator
sees its own inputs. The first step (compiles) is a warm-up and not timed.
The baseline is verified in the run: its input equals the ``fast-convex`` path's at every step
within :data:`U_ATOL` (else :class:`BaselineMismatch`). Thesis (YALMIP + MOSEK): 6 ms for 3
masses, 340 ms for 8; the issue's goal: 1 ms and 20 ms in Python. 8 masses (``2⁷ = 128``
vertices of ``Θ₀``; 20 steps, without the recompiling path) are run only when the design
(robust LMI over 128 vertices, contractive 𝕏₀ in 16 dimensions) finishes within
:data:`DESIGN_BUDGET_S`; else the row says "not measured" and why. ``quick``: 3 masses,
30 steps; the full run: 3 masses, 150 steps (the thesis' run length). :func:`step_split`
adds where the ``fast-convex`` step's time goes (estimator update, ``s_jr``, QP solver,
backend, bookkeeping); :func:`staged_hpipm` the stage-ordered (4.5) on HPIPM
(``"structured-sqp"``) against ``fast-convex``'s PIQP on the same states.
"""

from __future__ import annotations

import multiprocessing as mp
import time

import cvxpy as cp
import numpy as np

from balustrade.backends.cvxpy_backend import SOLVER_OPTIONS
from balustrade.control.rapsf import DEFAULT_TARGET, RAPSF, _small_vertices
from balustrade.design.rapsf import contractive_box, contractive_polytope, robust_gain
from balustrade.errors import BalustradeError
from balustrade.estimate import BoxUpdate
from balustrade.models.msd import msd_chain, msd_performance, msd_setup
from balustrade.problems.rapsf import (
    joint_constraints,
    model_matrices,
    s_constants,
    tube_constants,
    unit_polytope,
)
from benchmarks._timing import interleaved

THESIS_S = {3: 6e-3, 8: 0.340}
GOAL_S = {3: 1e-3, 8: 20e-3}
BASELINE = "cvxpy rebuilt every step"
#: baseline vs fast-convex: applied input (absolute)
U_ATOL = 1e-5
#: the 8-mass design must finish within this (seconds, in a child process)
DESIGN_BUDGET_S = 300.0


class BaselineMismatch(AssertionError):
    """The cvxpy baseline disagrees with balustrade on the same state."""


def design(n: int) -> dict:
    """The §4.7 design: ``K`` by the robust LMI over the vertices of ``Θ₀``, ``𝕏₀`` a
    λ-contractive box when one exists, else a contractive polytope."""
    system, st = msd_chain(n), msd_setup(n)
    V = st.Theta0.vertices()
    F, G = joint_constraints(st.X, st.U)
    K = robust_gain(system, V, contraction=0.95)
    try:
        X0 = contractive_box(system, K, V, st.W, F, G)
    except BalustradeError:
        X0 = contractive_polytope(system, K, V, st.W, F, G)
    return {"n": n, "system": system, "setup": st, "F": F, "G": G, "K": K, "X0": X0}


def _design_child(n: int, queue: mp.Queue) -> None:
    try:
        d = design(n)
        queue.put({"K": d["K"], "H": d["X0"].H, "h": d["X0"].h})
    except Exception as exc:  # noqa: BLE001 - reported as "not measured"
        queue.put({"error": f"{type(exc).__name__}: {exc}"})


def design_within(n: int, budget: float) -> tuple[dict | None, str]:
    """:func:`design` in a child process killed after ``budget`` seconds: ``(design, "")``
    or ``(None, why not)``."""
    from balustrade.dsl.sets import Polytope

    ctx = mp.get_context("fork")
    queue = ctx.Queue()
    proc = ctx.Process(target=_design_child, args=(n, queue))
    start = time.perf_counter()
    proc.start()
    try:     # read before join: a result larger than the pipe buffer blocks the child's exit
        out = queue.get(timeout=budget)
    except Exception:  # noqa: BLE001 - queue.Empty: no result within the budget
        out = None
    proc.join(5.0)
    if proc.is_alive():
        proc.terminate()
        proc.join()
    if out is None:
        if proc.exitcode not in (None, 0):
            return None, f"design failed: exit code {proc.exitcode}"
        return None, f"design did not finish within {budget:.0f} s"
    if "error" in out:
        return None, f"design failed: {out['error']}"
    system, st = msd_chain(n), msd_setup(n)
    F, G = joint_constraints(st.X, st.U)
    d = {"n": n, "system": system, "setup": st, "F": F, "G": G, "K": out["K"],
         "X0": Polytope(out["H"], out["h"], name="X0")}
    d["design_s"] = time.perf_counter() - start
    return d, ""


class RebuiltCvxpy:
    """Algorithm 4.1's optimal branch as the baseline: the box update, ``s_jr`` of the new
    vertices, (4.5) built from scratch in plain cvxpy and solved; ``u = K x + v₀``."""

    def __init__(self, d: dict):
        self.d = d
        system, st, X0 = d["system"], d["setup"], d["X0"]
        self.estimator = BoxUpdate(system, st.W, st.Theta0)
        self.Theta = st.Theta0
        c = tube_constants(X0, st.W, system, d["K"], st.Theta0.vertices(), d["F"], d["G"])
        self.HX, self.w_bar, self.t = unit_polytope(X0, "baseline"), c.w_bar, c.t
        self.X0_vertices = _small_vertices(X0)
        self.prev: tuple[np.ndarray, np.ndarray] | None = None
        self.bounds: list[tuple[np.ndarray, np.ndarray]] = []  # Θ_k per step (a box)

    def step(self, x: np.ndarray, u_p: np.ndarray) -> np.ndarray:
        d = self.d
        system, K, F, G, N = d["system"], d["K"], d["F"], d["G"], d["setup"].N
        if self.prev is not None:
            self.Theta = self.estimator.update(self.prev[0], self.prev[1], x)
        self.bounds.append((np.array(self.Theta.lb), np.array(self.Theta.ub)))
        V = np.atleast_2d(self.Theta.vertices())
        s = s_constants(d["X0"], system, K, V, self.X0_vertices)
        n, m = K.shape[1], K.shape[0]
        HX, ones = self.HX, np.ones((self.HX.shape[0], 1))
        z, alpha, v = cp.Variable((n, N + 1)), cp.Variable(N + 1, nonneg=True), \
            cp.Variable((m, N))
        cons = [HX @ (x - z[:, 0]) <= alpha[0]]
        for j, th in enumerate(V):
            A, B = model_matrices(system, th)
            cons.append(HX @ ((A + B @ K) @ z[:, :N] + B @ v - z[:, 1:])
                        + np.outer(s[:, j], np.ones(N)) @ cp.diag(alpha[:N])
                        + self.w_bar[:, None] <= ones @ cp.reshape(alpha[1:], (1, N),
                                                                  order="F"))
        cons += [(F + G @ K) @ z[:, :N] + np.outer(self.t, np.ones(N)) @ cp.diag(alpha[:N])
                 + G @ v <= 1, z[:, N] == 0, alpha[N] <= 1]
        prob = cp.Problem(cp.Minimize(cp.sum_squares(u_p - K @ x - v[:, 0])), cons)
        prob.solve(solver="PIQP", **SOLVER_OPTIONS["PIQP"])
        if prob.status != cp.OPTIMAL:
            raise BaselineMismatch(f"baseline solve: {prob.status}")
        u = K @ x + np.asarray(v.value)[:, 0]
        self.prev = (x, u)
        return u


class Loop:
    """One closed loop of a path: the §4.7 chain with ``θ*`` and the disturbances of seed 0
    (the same for every path), the aggressive proposal, ``step`` the path's controller."""

    def __init__(self, d: dict, step, steps: int):
        system, st = d["system"], d["setup"]
        rng = np.random.default_rng(0)
        self.theta = st.sample_theta(rng)
        self.ws = rng.uniform(-st.W.ub, st.W.ub, size=(steps, 2 * d["n"]))
        self.d, self.step, self.system = d, step, system
        self.x = st.x0.copy()
        self.applied: list[np.ndarray] = []
        self.times: list[float] = []
        self.fallbacks = 0  # steps that did not apply a fresh optimal solve

    def __call__(self, k: int) -> None:
        u_p = msd_performance(k, self.x, self.d["n"])
        t0 = time.perf_counter()
        u, info = self.step(self.x, u_p)
        self.times.append(time.perf_counter() - t0)
        self.applied.append(u)
        self.fallbacks += info is not None and info.fallback is not None
        self.x = self.system.step(self.x, u, self.theta, self.ws[k])


def _controller(d: dict, target: str, vertex_data: str) -> RAPSF:
    system, st = d["system"], d["setup"]
    return RAPSF(system, d["X0"], d["F"], d["G"], st.W, d["K"], st.N, st.Theta0,
                 estimator=BoxUpdate(system, st.W, st.Theta0), target=target,
                 vertex_data=vertex_data)


def every_row(ctrl: RAPSF) -> RAPSF:
    """``ctrl`` solving (4.5) with every tube row written per vertex (no rows shared between
    vertices, not factored): the form before the row reductions, for comparison. Only the
    controller's own bound methods are replaced (instance attributes)."""
    problem = ctrl._problem
    ctrl._shared_rows = lambda n_th: None
    ctrl._problem = lambda horizon, **kw: problem(horizon, **{**kw, "factored": False})
    return ctrl


def bench_size(d: dict, steps: int, constants: bool = True) -> list[dict]:
    """The paths on ``steps`` states of ``d``'s chain (without the recompiling ``fast-convex
    constants`` path unless ``constants``)."""
    n = d["n"]
    paths = {"default": _controller(d, DEFAULT_TARGET, "parameters"),
             "fast-convex": _controller(d, "fast-convex", "parameters"),
             "fast-convex every row": every_row(_controller(d, "fast-convex",
                                                            "parameters")),
             "fast-convex-conic": _controller(d, "fast-convex-conic", "parameters"),
             "fast-convex constants": _controller(d, "fast-convex", "constants"),
             "exact": _controller(d, "exact", "parameters")}
    if not constants:
        del paths["fast-convex constants"]
    baseline = RebuiltCvxpy(d)
    loops = {k: Loop(d, c.step, steps) for k, c in paths.items()}
    loops[BASELINE] = Loop(d, lambda x, u_p: (baseline.step(x, u_p), None), steps)
    for loop in loops.values():
        loop(0)                                        # warm-up: compiles
        loop.times.clear()
        loop.fallbacks = 0
    times = interleaved(loops, range(1, steps), block=10)
    ref = np.array(loops["fast-convex"].applied)
    gap = float(np.max(np.abs(np.array(loops[BASELINE].applied) - ref)))
    if gap > U_ATOL:
        raise BaselineMismatch(f"{n} masses: the cvxpy baseline's input differs from "
                               f"fast-convex's by {gap:.3g} > {U_ATOL:g}")
    changes = int(np.count_nonzero(np.any(np.diff(np.array(
        [np.r_[lo, hi] for lo, hi in baseline.bounds]), axis=0) != 0, axis=1)))
    rows = []
    t_base = times[BASELINE]
    for k in [*paths, BASELINE]:
        loop = loops[k]
        row = {"name": f"rapsf {n} masses Alg 4.1 step: {k}", "median_s": times[k],
               "mean_s": float(np.mean(loop.times)), "max_s": float(np.max(loop.times))}
        if k != BASELINE:
            row.update(baseline=BASELINE, ratio=t_base / times[k],
                       max_du_vs_fast_convex=float(np.max(np.abs(np.array(loop.applied)
                                                                 - ref))),
                       fallbacks=loop.fallbacks, target=paths[k].target.name,
                       engine=paths[k].engine,
                       update_lp_steps=sum(r.lps > 0 for r in paths[k].estimator.history))
        row.update(goal_s=GOAL_S[n], vs_thesis=THESIS_S[n] / times[k], steps=steps - 1,
                   n_vertices=int(len(d["setup"].Theta0.vertices())),
                   tube_rows=int(d["X0"].H.shape[0]), theta_changes=changes)
        if k != BASELINE and paths[k].parametric:
            program = getattr(next(iter(paths[k]._compiled.values())), "program", None)
            if program is not None:
                row.update(qp_rows=int(program.A.shape[0]), qp_nnz=int(program.A.nnz))
        rows.append(row)
    return rows



def timed_into(fn, acc: dict, part: str):
    """``fn`` wrapped to add its wall time to ``acc[part]`` on every call (also when it
    raises)."""
    def call(*args, **kwargs):
        t0 = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            acc[part] = acc.get(part, 0.0) + time.perf_counter() - t0
    return call


def step_split(d: dict, steps: int, target: str = "fast-convex") -> list[dict]:
    """Where one ``controller.step`` of the parametric path spends its time, per step:
    the estimator's update (nonfalsified set, support LPs, records), the new vertices and
    ``s_jr`` of ``Θ_k`` (``_set_theta``, only on steps where ``Θ_k`` changed), the solver
    engine's run (the QP solver's update and solve) and the rest of the backend's ``solve``
    (parameter packing, ``q``/``b``/``A(p)``, the :class:`~balustrade.backends.Solution`),
    and the remainder of the step (Algorithm 4.1's bookkeeping, ``StepInfo``). Each part is
    timed by wrapping the controller's own bound methods (instance attributes, nothing else
    is touched); ``mean_s`` is the mean over all steps (a part not run on a step counts 0)."""
    ctrl = _controller(d, target, "parameters")
    loop = Loop(d, ctrl.step, steps)
    loop(0)                                                   # warm-up: compiles
    acc: dict[str, float] = {}

    def timed(fn, part):
        return timed_into(fn, acc, part)

    ctrl.estimator.update = timed(ctrl.estimator.update, "estimator update")
    ctrl._set_theta = timed(ctrl._set_theta, "vertices and s of a new Θ_k")
    for compiled in ctrl._compiled.values():
        compiled.solve = timed(compiled.solve, "backend solve")
        compiled.engine.run = timed(compiled.engine.run, "solver engine run")
    parts = ["estimator update", "vertices and s of a new Θ_k", "solver engine run",
             "backend solve, rest", "step, rest"]
    per: dict[str, list[float]] = {k: [] for k in ["step", *parts]}
    for k in range(1, steps):
        acc.clear()
        loop(k)
        total = loop.times[-1]
        acc["backend solve, rest"] = acc.get("backend solve", 0.0) - acc.get(
            "solver engine run", 0.0)
        acc["step, rest"] = total - sum(acc.get(p, 0.0) for p in parts[:2]) - acc.get(
            "backend solve", 0.0)
        per["step"].append(total)
        for p in parts:
            per[p].append(acc.get(p, 0.0))
    return [{"name": f"rapsf {d['n']} masses Alg 4.1 step split ({target}): {p}",
             "median_s": float(np.median(v)), "mean_s": float(np.mean(v)),
             "steps": steps - 1} for p, v in per.items()]


def reduced_vs_every_row(d: dict, steps: int, block: int = 10) -> list[dict]:
    """CPU time (``time.process_time``: robust to the other jobs on a loaded machine) per
    ``controller.step`` of ``fast-convex`` with the reduced rows of (4.5c) (the default) and
    with every row (:func:`every_row`), two closed loops interleaved in blocks of ``block``
    steps; raises :class:`BaselineMismatch` if their inputs differ by more than
    :data:`U_ATOL`. For 8 masses pass the design of
    :func:`balustrade.reproduce.msd_adaptive.design` (the parallelotope 𝕏₀)."""
    ctrls = {"reduced rows": _controller(d, "fast-convex", "parameters"),
             "every row": every_row(_controller(d, "fast-convex", "parameters"))}
    loops = {k: Loop(d, c.step, steps) for k, c in ctrls.items()}
    cpu: dict[str, list[float]] = {k: [] for k in ctrls}
    for loop in loops.values():
        loop(0)                                        # warm-up: compiles
    for i in range(1, steps, block):
        for k, loop in loops.items():
            for j in range(i, min(i + block, steps)):
                c0 = time.process_time()
                loop(j)
                cpu[k].append(time.process_time() - c0)
    gap = float(np.max(np.abs(np.array(loops["reduced rows"].applied)
                              - np.array(loops["every row"].applied))))
    if gap > U_ATOL:
        raise BaselineMismatch(f"reduced rows and every row differ by {gap:.3g}")
    rows = []
    for k, ctrl in ctrls.items():
        program = getattr(next(iter(ctrl._compiled.values())), "program", None)
        rows.append({"name": f"rapsf {d['n']} masses Alg 4.1 step CPU: fast-convex {k}",
                     "median_s": float(np.median(cpu[k])),
                     "p90_s": float(np.percentile(cpu[k], 90)),
                     "wall_median_s": float(np.median(loops[k].times)), "steps": steps - 1,
                     "max_du": gap, "fallbacks": loops[k].fallbacks,
                     **({} if program is None else {"qp_rows": int(program.A.shape[0]),
                                                    "qp_nnz": int(program.A.nnz)})})
    return rows


def staged_hpipm(d: dict, steps: int = 20, every: int = 4, repeats: int = 3) -> list[dict]:
    """(4.5) in stage order (``rapsf_problem(staged=True)``) on ``"structured-sqp"``
    (``sqpmethod`` with HPIPM's Riccati-based interior point, the stage-order pass) against
    the ``fast-convex`` controller's own compiled problem (PIQP), both with the same rows
    (shared, factored as the controller builds them) and the same vertex data (Θ₀), on
    every ``every``-th state of a ``steps``-step closed loop of ``fast-convex``; the two
    solves interleaved ``repeats`` times per state (wall time, medians). ``max_du``: the
    largest difference of the applied input ``K x + v₀`` where both report optimal."""
    from balustrade.backends import compile as compile_problem

    ctrl = _controller(d, "fast-convex", "parameters")
    loop = Loop(d, ctrl.step, steps)
    states = []
    for k in range(steps):
        states.append((k, loop.x.copy()))
        loop(k)
    n_th = ctrl._n_compiled
    rep = ctrl._shared_rows(n_th)
    fast = next(iter(ctrl._compiled.values()))
    t0 = time.perf_counter()
    staged = compile_problem(ctrl._problem(d["setup"].N, n_vertices=n_th, shared=rep,
                                           staged=True), "structured-sqp")
    compile_s = time.perf_counter() - t0
    ctrl.reset()
    idx = np.arange(n_th) % len(ctrl.vertices)
    times: dict[str, list[float]] = {"fast-convex": [], "structured-sqp staged": []}
    gaps, both_optimal, staged_optimal = [], 0, 0
    for k, x in states[::every]:
        params = {"x0": x, "u_p": msd_performance(k, x, d["n"]),
                  "theta": ctrl.vertices[idx].T, "s": ctrl._s[:, idx]}
        for _ in range(repeats):
            t = time.perf_counter()
            a = fast.solve(params)
            times["fast-convex"].append(time.perf_counter() - t)
            t = time.perf_counter()
            b = staged.solve(params)
            times["structured-sqp staged"].append(time.perf_counter() - t)
        staged_optimal += b.status == "optimal"
        if a.status == "optimal" and b.status == "optimal":
            both_optimal += 1
            gaps.append(float(np.max(np.abs(np.asarray(a["v"])[:, 0]
                                            - np.asarray(b["v"])[:, 0]))))
    qp = staged.options["qpsol_options"]
    return [{"name": f"rapsf {d['n']} masses (4.5) solve: {k}",
             "median_s": float(np.median(v)), "states": len(states[::every]),
             "max_du": max(gaps) if gaps else None, "both_optimal": both_optimal,
             "staged_optimal": staged_optimal,
             **({"compile_s": compile_s, "stage_nx": qp["nx"][0], "stage_nu": qp["nu"][0],
                 "stage_ng": max(qp["ng"])} if k != "fast-convex" else {})}
            for k, v in times.items()]


def run(quick: bool = False) -> list[dict]:
    d3 = design(3)
    rows = bench_size(d3, 30 if quick else 150) + step_split(d3, 30 if quick else 150) \
        + reduced_vs_every_row(d3, 60 if quick else 150) \
        + staged_hpipm(d3, 8 if quick else 20)
    if quick:
        return rows
    d8, why = design_within(8, DESIGN_BUDGET_S)
    if d8 is None:
        return rows + [{"name": "rapsf 8 masses Alg 4.1 step", "status": "not measured",
                        "reason": why}]
    rows8 = bench_size(d8, 20, constants=False)  # a compile per changed Θ_k: minutes
    for row in rows8:
        row["design_s"] = d8["design_s"]
    return rows + rows8
