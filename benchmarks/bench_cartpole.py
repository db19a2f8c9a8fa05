"""Cart-pole PCBF pair (2.24)+(2.23), N = 20, RK4 (issue #14, nonlinear case): the
``fast-sqp`` target in Python and its emitted C, on the closed loop of
:func:`balustrade.examples.cartpole.cartpole_scenario` (tilted pole, destabilizing proposal).

Reported, not asserted (goals of the issue: C median <= 5 ms, worst <= 20 ms, 0 failures in
100 steps, C = Python within 1e-6, build in seconds):

* Python: median and worst step, steps with a fallback or a non-``ok`` status ("failures");
* C through ctypes (:class:`~balustrade.codegen.runtime.CPCBFSafetyFilter`), on the same
  closed loop run by the C itself: median and worst step, failures, max ``|u_C − u_Py|`` at
  the Python loop's states (C and Python interleaved state by state);
* C source size (bytes of ``*_casadi.c`` + glue) and build time (``cc -O3 -Werror``).

Times are taken on a shared machine: under load; ratios come from one interleaved run.

:func:`run_structured` (``python -m benchmarks.bench_cartpole structured``): the same closed
loop from Python with ``fast-sqp`` and ``structured-ip`` (fatrop) interleaved step by step
(each target its own loop), and fatrop's CasADi-generated C (``nlpsol.generate``, linked to
libfatrop/libblasfeo of the casadi wheel) for (2.24) and (2.23) at the states of the
``structured-ip`` loop: one solve in C against the same solve from Python, interleaved.
"""

from __future__ import annotations

import os
import subprocess
import tempfile
import time
from pathlib import Path

import casadi as ca
import numpy as np

from balustrade.backends import compile as compile_problem
from balustrade.backends import resolve_target
from balustrade.codegen import CPCBFSafetyFilter, build, emit_pcbf
from balustrade.control import PCBFSafetyFilter
from balustrade.examples.cartpole import cartpole_design, cartpole_problems, cartpole_scenario
from balustrade.problems.pcbf import pcbf_filter_problem, pcbf_slack_problem


def _failure(info: object) -> bool:
    return bool(info.fallback) or info.status != "ok"


def run(quick: bool = False) -> list[dict]:
    steps = 20 if quick else 100
    d = cartpole_design()
    slack, filt = cartpole_problems("fast-sqp", design=d)
    py = PCBFSafetyFilter(slack, filt, d.U)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "cartpole"
        emitted = emit_pcbf(py, "cartpole", out)
        size = sum(p.stat().st_size for p in emitted.sources + emitted.headers)
        t0 = time.perf_counter()
        lib = build(out, emitted.name, werror=True)
        build_s = time.perf_counter() - t0
        c = CPCBFSafetyFilter(lib)
        # Python's closed loop; the C step at each of its states, interleaved (C warm
        # starts follow the Python trajectory, as a deployed filter's would)
        x0, proposal = cartpole_scenario()
        x, t_py, t_c, fail_py, fail_c, diff, inside = x0.copy(), [], [], 0, 0, 0.0, True
        for k in range(steps):
            u_p = proposal(x, k)
            t = time.perf_counter()
            u, info = py.step(x, u_p)
            t_py.append(time.perf_counter() - t)
            t = time.perf_counter()
            u_c, info_c = c.step(x, u_p)
            t_c.append(time.perf_counter() - t)
            fail_py += _failure(info)
            fail_c += _failure(info_c)
            diff = max(diff, float(np.max(np.abs(u_c - u))))
            x = d.system.step(x, u)
            inside = inside and bool(np.all(np.abs(x) <= d.X.h[:4] + 1e-9))
    rows.append({"name": f"cartpole pcbf step, Python fast-sqp ({steps} steps)",
                 "median_s": float(np.median(t_py)), "worst_ms": round(1e3 * max(t_py), 1),
                 "failures": fail_py, "stays_in_X": inside})
    rows.append({"name": f"cartpole pcbf step, C via ctypes ({steps} steps)",
                 "median_s": float(np.median(t_c)), "worst_ms": round(1e3 * max(t_c), 1),
                 "failures": fail_c, "max_du_vs_python": float(f"{diff:.3g}")})
    rows.append({"name": "cartpole pcbf C module", "median_s": build_s,
                 "source_bytes": size, "note": "median_s = build time (cc -O3 -Werror)"})
    return rows


def _loop_row(name: str, times: list[float], fails: int, inside: bool) -> dict:
    return {"name": name, "median_ms": round(1e3 * float(np.median(times)), 2),
            "worst_ms": round(1e3 * max(times), 1), "failures": fails, "stays_in_X": inside}


def _fatrop_c(ocp: object, tmp: Path, tag: str) -> tuple:
    """``(python solver, C solver, build s, source bytes)`` for fatrop alone on ``ocp``: the
    solver's CasADi C (``generate``) compiled ``-O2`` against the casadi wheel's libfatrop
    and libblasfeo, loaded with ``casadi.external``."""
    c = compile_problem(ocp, "structured-ip-noretry")
    libs = resolve_target("structured-ip").c_libraries()
    cdir = Path(ca.__file__).parent
    src = tmp / f"{tag}.c"
    cwd = os.getcwd()
    os.chdir(tmp)
    try:
        c.solver.generate(src.name, {"with_header": False})
    finally:
        os.chdir(cwd)
    lib = tmp / f"lib{tag}.so"
    t0 = time.perf_counter()
    subprocess.run(["gcc", "-shared", "-fPIC", "-O2", "-o", str(lib), str(src),
                    f"-I{cdir / 'include'}", f"-I{cdir / 'include' / 'fatrop'}", f"-L{cdir}",
                    f"-Wl,-rpath,{cdir}", *[f"-l{x}" for x in libs], "-lm"], check=True,
                   capture_output=True, timeout=600)
    build_s = time.perf_counter() - t0
    return c, ca.external(c.solver.name(), str(lib)), build_s, src.stat().st_size


def run_structured(steps: int = 100) -> list[dict]:
    """Python closed loops (``fast-sqp``, ``structured-ip``) and fatrop in C (module doc)."""
    d = cartpole_design()
    loops = {t: PCBFSafetyFilter(*cartpole_problems(t, design=d), d.U)
             for t in ("fast-sqp", "structured-ip")}
    x0, proposal = cartpole_scenario()
    state = {t: x0.copy() for t in loops}
    times = {t: [] for t in loops}
    fails, inside = dict.fromkeys(loops, 0), dict.fromkeys(loops, True)
    visited = []
    for k in range(steps):
        for t, filt in loops.items():
            x = state[t]
            if t == "structured-ip":
                visited.append((x.copy(), proposal(x, k)))
            start = time.perf_counter()
            u, info = filt.step(x, proposal(x, k))
            times[t].append(time.perf_counter() - start)
            fails[t] += _failure(info)
            state[t] = d.system.step(x, u)
            inside[t] = inside[t] and bool(np.all(np.abs(state[t]) <= d.X.h[:4] + 1e-9))
    rows = [_loop_row(f"cartpole pcbf step, Python {t} ({steps} steps)", times[t], fails[t],
                      inside[t]) for t in loops]
    args = (d.system, d.X, d.U, d.h_f, d.N, d.deltas)
    slack_ocp = pcbf_slack_problem(*args, alpha_f=d.alpha_f, slack_norm=1)
    exact = compile_problem(slack_ocp, "exact")
    with tempfile.TemporaryDirectory() as tmp:
        for tag, ocp in (("slack", slack_ocp), ("filter", pcbf_filter_problem(*args))):
            py, cf, build_s, size = _fatrop_c(ocp, Path(tmp), f"cartpole_{tag}")
            t_py, t_c, diff, failed = [], [], 0.0, 0
            for x, u_p in visited:
                par = {"x0": x}
                if tag == "filter":
                    sol = exact.solve(par)
                    par = {**par, "u_p": u_p, "xi": sol.primal["xi"], "xi_N": sol.primal["xi_N"]}
                pv = ocp.pack_parameters(par)
                kw = {"x0": py._initial_guess(None, pv)[0], "p": pv, "lbx": py.lbx,
                      "ubx": py.ubx, "lbg": py.lbg, "ubg": py.ubg}
                start = time.perf_counter()
                r_py = py.solver(**kw)
                t_py.append(time.perf_counter() - start)
                failed += not py.solver.stats()["success"]
                start = time.perf_counter()
                r_c = cf(**kw)
                t_c.append(time.perf_counter() - start)
                diff = max(diff, float(np.max(np.abs(np.asarray(r_c["x"] - r_py["x"])))))
            rows.append({"name": f"cartpole ({'2.24' if tag == 'slack' else '2.23'}) fatrop, "
                         f"Python vs C ({len(visited)} states)",
                         "py_median_ms": round(1e3 * float(np.median(t_py)), 2),
                         "c_median_ms": round(1e3 * float(np.median(t_c)), 2),
                         "c_worst_ms": round(1e3 * max(t_c), 1),
                         "fatrop_unconverged": failed, "max_dx_c_vs_py": float(f"{diff:.3g}"),
                         "build_s": round(build_s, 1), "source_bytes": size})
    return rows


if __name__ == "__main__":  # pragma: no cover
    import sys

    for row in (run_structured() if "structured" in sys.argv[1:] else run()):
        print(row)
