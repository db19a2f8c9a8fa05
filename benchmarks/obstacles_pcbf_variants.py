"""Variants of the §8.3 PCBF algorithm's (2.23) chain, decision by decision (Python;
issue #16/#14, session 14, docs/obstacles.md "session 14").

``python -m benchmarks.obstacles_pcbf_variants stall [--variants "off;1e-3,20;1e-3,10"]
[--states 200]``
    The filters of :func:`~balustrade.reproduce.obstacles.pcbf_algorithm`
    (``structured-ip``, ``shifted=False``) with fatrop's stall stop ``(tol_acceptable,
    acceptable_iter)`` per variant (``off``: none), run in lockstep over the 5 reference
    closed loops (each variant its own loop and naive MPC) and at ``--states`` cold random
    states: every step where a variant's attempts (problem, solver, message, iterations) or
    input differ from the first variant's is printed, then the step times per variant.

``python -m benchmarks.obstacles_pcbf_variants ipopt-first``
    Along the 5 reference loops (the chain as it is), at every certified step: the time
    of the chain's (2.23) solve and, on the side (not used), the time of the chain's last
    solver (IPOPT) from the certified shifted plan — what running that attempt *first*
    would cost — with iterations, statuses and the objective difference.

``python -m benchmarks.obstacles_pcbf_variants fatrop-plan``
    Along the 5 reference loops (the chain as it is, with the stall stop), at every
    certified step whose first (2.23) attempt fails: the process CPU time of the chain's
    attempts after it (IPOPT from the certified plan) and, on the side (not used), of
    fatrop from the plan followed, if that fails, by IPOPT from the plan (session 12's
    second attempt put before session 13's).

Times are wall times under the machine's load unless said otherwise.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np

from balustrade.control.plant import check_plant
from balustrade.models.obstacle_car import obstacle_car
from balustrade.reproduce import obstacles as O
from benchmarks.obstacles_pcbf_c import random_states


def _parse(spec: str) -> tuple[float, int] | None:
    if spec == "off":
        return None
    tol, iters = spec.split(",")
    return float(tol), int(iters)


def _recorded(stall: tuple[float, int] | None) -> tuple[object, list]:
    """The Python PCBF algorithm with ``stall`` and a list that records every attempt of
    its two problems as (problem, solver, message, iterations)."""
    f = O.pcbf_algorithm("structured-ip", shifted=False, stall_stop=stall)
    calls: list = []
    for name in ("slack", "filter"):
        prob = getattr(f, name)
        prob._retry_solvers()  # built before any step is timed
        inner = prob._solve_with

        def rec(solver, p, guess, inner=inner, name=name):
            s = inner(solver, p, guess)
            calls.append((name, s.solver, s.message.split(" (after")[0][:32], s.iterations))
            return s

        prob._solve_with = rec
    return f, calls


def _step(f, calls: list, x: np.ndarray, u_p: np.ndarray) -> tuple:
    calls.clear()
    t = time.perf_counter()
    u, info = f.step(x, u_p)
    return u, info.status, list(calls), 1e3 * (time.perf_counter() - t)


def _report(where: str, base: tuple, name: str, other: tuple) -> None:
    du = float(np.max(np.abs(other[0] - base[0])))
    if other[2] != base[2] or du > 0:
        print(f"{where}: largest input difference {du:.3g}\n"
              f"   {'first':>10}: {base[1]}, {base[3]:.0f} ms, {base[2]}\n"
              f"   {name:>10}: {other[1]}, {other[3]:.0f} ms, {other[2]}", flush=True)


def _stats(t: list[float]) -> str:
    a = np.asarray(t)
    return f"median {np.median(a):.1f} / 90th {np.percentile(a, 90):.1f} / worst {a.max():.0f} ms"


def stall(variants: list[str], n_states: int) -> None:
    filters = {v: _recorded(_parse(v)) for v in variants}
    plant = check_plant(obstacle_car(), "obstacles_pcbf_variants")
    times: dict[str, list[float]] = {v: [] for v in variants}
    for p in O.STARTS:
        x0 = O.initial_state(p)
        xs = {v: x0.copy() for v in variants}
        mpcs = {v: O.NaiveMPC() for v in variants}
        for v in variants:
            mpcs[v].start(x0)
            filters[v][0].reset()
        for k in range(O.STEPS):
            out = {}
            for v in variants:
                out[v] = _step(*filters[v], xs[v], mpcs[v](k, xs[v]))
                times[v].append(out[v][3])
                xs[v] = plant.step(xs[v], out[v][0], None)
            for v in variants[1:]:
                _report(f"loop {p} step {k}", out[variants[0]], v, out[v])
    for v in variants:
        print(f"loops {v}: {_stats(times[v])}")
    cold: dict[str, list[float]] = {v: [] for v in variants}
    for i, (x, u_p) in enumerate(zip(*random_states(n_states))):
        out = {}
        for v in variants:
            filters[v][0].reset()
            out[v] = _step(*filters[v], x, u_p)
            cold[v].append(out[v][3])
        for v in variants[1:]:
            _report(f"cold state {i}", out[variants[0]], v, out[v])
    if n_states:
        for v in variants:
            print(f"cold {v}: {_stats(cold[v])}")


def ipopt_first() -> None:
    f = O.pcbf_algorithm("structured-ip", shifted=False)
    filt = f.filter
    ipopt = filt._retry_solvers()[-1]
    solve = filt.solve
    rows: list[tuple] = []

    def timed(params=None, warm_start=None, second_start=None, second_solver=0, lead=None):
        t = time.perf_counter()
        s = solve(params, warm_start, second_start, second_solver, lead)
        t_chain = 1e3 * (time.perf_counter() - t)
        if second_start is not None:  # a certified step: its plan is the second start
            p = filt.ocp.pack_parameters(params)
            t = time.perf_counter()
            s2 = filt._solve_with(ipopt, p, filt._initial_guess(second_start, p))
            rows.append((t_chain, 1e3 * (time.perf_counter() - t), s.iterations,
                         s2.iterations, str(s2.status), s2.objective - s.objective))
        return s

    filt.solve = timed
    _drive(f)
    print(f"certified steps: {len(rows)}")
    for j, what in ((0, "the chain (fatrop first)"), (1, "IPOPT from the plan")):
        its = [r[2 + j] for r in rows]
        print(f"{what}: {_stats([r[j] for r in rows])}, iterations median "
              f"{np.median(its):.0f}, largest {max(its)}")
    print("IPOPT from the plan, statuses:", {s: sum(r[4] == s for r in rows)
                                             for s in sorted({r[4] for r in rows})})
    d = [r[5] for r in rows]
    print(f"objective (IPOPT from the plan − chain): {min(d):.3g} … {max(d):.3g}")


def _drive(f: object, after_step: Callable[[tuple, int], None] | None = None) -> None:
    """The PCBF algorithm ``f`` filtering the naive MPC from every start of §8.3 for
    ``O.STEPS`` steps, without disturbance; ``after_step(start, k)`` after each step."""
    plant = check_plant(obstacle_car(), "obstacles_pcbf_variants")
    for p in O.STARTS:
        x, mpc = O.initial_state(p), O.NaiveMPC()
        mpc.start(x)
        f.reset()
        for k in range(O.STEPS):
            u, _ = f.step(x, mpc(k, x))
            x = plant.step(x, u, None)
            if after_step is not None:
                after_step(p, k)


def fatrop_plan() -> None:
    f = O.pcbf_algorithm("structured-ip", shifted=False)
    filt = f.filter
    fatrop, ipopt = filt.solver, filt._retry_solvers()[-1]
    solve = filt.solve
    rows: list[tuple] = []

    def cpu_solve(solver, p, guess) -> tuple:
        t = time.process_time()
        s = filt._solve_with(solver, p, guess)
        return s, 1e3 * (time.process_time() - t)

    def timed(params=None, warm_start=None, second_start=None, second_solver=0, lead=None):
        if second_start is None:
            return solve(params, warm_start, second_start, second_solver, lead)
        p = filt.ocp.pack_parameters(params)
        first, t0 = cpu_solve(fatrop, p, filt._initial_guess(warm_start, p))
        if not first.success:
            plan = filt._initial_guess(second_start, p)
            s_ip, t_ip = cpu_solve(ipopt, p, plan)
            s_fp, t_fp = cpu_solve(fatrop, p, plan)
            t_alt, alt = t_fp, s_fp
            if not s_fp.success:
                alt, t2 = cpu_solve(ipopt, p, plan)
                t_alt += t2
            rows.append((t0, t_ip, t_alt, s_fp.message[:28], s_fp.iterations,
                         alt.success, float(alt.objective - s_ip.objective)))
        return solve(params, warm_start, second_start, second_solver, lead)

    filt.solve = timed

    def tag(p: tuple, k: int) -> None:       # the start and step of a row just recorded
        if rows and len(rows[-1]) == 7:
            rows[-1] = (*rows[-1], p, k)
    _drive(f, tag)
    print("CPU ms: first attempt + (IPOPT from the plan | fatrop from the plan [+ IPOPT])")
    for r in rows:
        print(f"  {r[7]} step {r[8]}: {r[0]:.1f} + ({r[1]:.1f} | {r[2]:.1f}); fatrop from the "
              f"plan: {r[3]}, {r[4]} iterations; converged {r[5]}, objective "
              f"difference {r[6]:.3g}")
    if rows:
        print(f"largest step: {max(r[0] + r[1] for r in rows):.1f} (as it is) | "
              f"{max(r[0] + r[2] for r in rows):.1f} (fatrop from the plan first)")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("mode", choices=("stall", "ipopt-first", "fatrop-plan"))
    ap.add_argument("--variants", default="off;1e-3,20",
                    help="';'-separated TOL,ITERS or 'off'; the first is the reference")
    ap.add_argument("--states", type=int, default=200)
    a = ap.parse_args(argv)
    if a.mode == "stall":
        stall(a.variants.split(";"), a.states)
    elif a.mode == "ipopt-first":
        ipopt_first()
    else:
        fatrop_plan()


if __name__ == "__main__":
    main()
