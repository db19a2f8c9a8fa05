"""Cart-pole PCBF pair (2.24)+(2.23), N = 20, RK4 (issue #14, nonlinear case): the
``fast-sqp`` target in Python and its emitted C, on the closed loop of
:func:`balustrade.examples.cartpole.cartpole_scenario` (tilted pole, destabilizing proposal).

Reported, not asserted (goals of the issue: C median <= 5 ms, worst <= 20 ms, 0 failures in
100 steps, C = Python within 1e-6, build in seconds):

* Python: median and worst step, steps with a fallback or a status that is not a success
  (:func:`~balustrade.control.base.step_succeeded`: ``ok`` or ``certified``) ("failures");
* C through ctypes (:class:`~balustrade.codegen.runtime.CPCBFSafetyFilter`), on the same
  closed loop run by the C itself: median and worst step, failures, max ``|u_C − u_Py|`` at
  the Python loop's states (C and Python interleaved state by state);
* C source size (bytes of ``*_casadi.c`` + glue) and build time (``cc -O3 -Werror``).

Times are taken on a shared machine: under load; ratios come from one interleaved run.

:func:`run_structured` (``python -m benchmarks.bench_cartpole structured [steps] [--sqp]``):
the same closed loop on the ``structured-ip`` target (fatrop) from Python and the emitted C
step of the same filter (:func:`~balustrade.codegen.emit_pcbf`: one call per step, linked to
libfatrop/libblasfeo/libipopt of the casadi wheel) at each state of the Python loop,
interleaved: step times, fatrop iterations per solve ((2.24): over the steps that solved
it, skipped steps counted apart), C = Python, source size and build
time; ``--sqp`` adds the ``fast-sqp`` loop from Python (interleaved, its own loop);
the default pair checks the shifted-plan certificate first (``certificate_first``, the
default since session 11); ``--no-certificate-first`` adds the same pair built with
``certificate_first=False`` (Python and its own emitted C, its own closed loop, interleaved
step by step with the default one): median/worst, steps whose (2.24) was skipped, failures,
max ``|Δu|``/``|Δx|`` against the default loop and whether X is kept.

:func:`run_warm_starts` (``python -m benchmarks.bench_cartpole warm [steps]``): fatrop's
iterations per solve under warm-start rules and options (Python, interleaved; every
(2.24) solved, ``certificate_first=False``, so that its iterations are measured).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from balustrade.codegen import CPCBFSafetyFilter, build, emit_pcbf
from balustrade.control import PCBFSafetyFilter
from balustrade.control.base import step_succeeded
from balustrade.examples.cartpole import cartpole_design, cartpole_problems, cartpole_scenario


def _failure(info: object) -> bool:
    """A fallback or a step that did not succeed (``ok``, or (2.24) skipped and
    ``certified``: :func:`~balustrade.control.base.step_succeeded`)."""
    return bool(info.fallback) or not step_succeeded(info.status)


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


def _iterations(info: object) -> tuple[int, int]:
    """Solver iterations of the step's (2.24) and (2.23) (0 when not solved)."""
    sols = info.solutions or {}
    return tuple(int(getattr(sols.get(k), "iterations", 0) or 0) for k in ("slack", "filter"))


def slack_iteration_stats(its: np.ndarray, skipped: list[bool]) -> dict:
    """(2.24)'s iterations over the steps that solved it (a step whose (2.24) was skipped
    by ``certificate_first`` ran no solver; counting it as 0 iterations lowered the
    median), and the skipped steps counted separately."""
    its, skipped = np.asarray(its).reshape(-1, 2), np.asarray(skipped, bool)
    solved = its[~skipped, 0]
    return {"skipped_slack_solves": int(skipped.sum()), "slack_solved_steps": len(solved),
            "slack_iters_median": float(np.median(solved)) if len(solved) else None,
            "slack_iters_max": int(solved.max()) if len(solved) else None}


def _emit_structured(py: PCBFSafetyFilter, name: str, tmp: str
                     ) -> tuple[CPCBFSafetyFilter, float, float, int]:
    """``py``'s emitted C step (fatrop), built: the runtime, emit and build seconds, and the
    source bytes."""
    out = Path(tmp) / name
    t0 = time.perf_counter()
    emitted = emit_pcbf(py, name, out, allow_external=True)
    emit_s = time.perf_counter() - t0
    size = sum(p.stat().st_size for p in emitted.sources + emitted.headers)
    t0 = time.perf_counter()
    lib = build(out, emitted.name, werror=True,
                extra_flags=tuple(emitted.manifest["link_flags"]))
    return CPCBFSafetyFilter(lib), emit_s, time.perf_counter() - t0, size


def run_structured(steps: int = 100, with_sqp: bool = False,
                   compare_off: bool = False) -> list[dict]:
    """The closed loop of :func:`~balustrade.examples.cartpole.cartpole_scenario` on the
    ``structured-ip`` target (fatrop) from Python, and its emitted C step
    (:func:`~balustrade.codegen.emit_pcbf`, one call per step through ctypes, linked to
    the casadi wheel's libfatrop/libblasfeo/libipopt) at every state of the Python loop,
    interleaved step by step: median and worst step, fatrop iterations per solve (the C
    runs the same solver from the same warm starts: its iterations are Python's),
    failures, max ``|u_C − u_Py|``, status mismatches; the C's source size and build time.
    ``with_sqp``: also the ``fast-sqp`` loop from Python, interleaved (its own loop).
    The default pair checks the shifted-plan certificate first (``certificate_first``, the
    filter's default): ``skipped_slack_solves`` counts the steps whose (2.24) it skipped.
    ``compare_off``: also the pair with ``certificate_first=False`` in Python and C (its own
    loop, the C at the states of that Python loop), interleaved step by step."""
    d = cartpole_design()
    x0, proposal = cartpole_scenario()
    py = PCBFSafetyFilter(*cartpole_problems("structured-ip", design=d), d.U)
    sqp = PCBFSafetyFilter(*cartpole_problems("fast-sqp", design=d), d.U) if with_sqp \
        else None
    off_py = PCBFSafetyFilter(py.slack, py.filter, d.U, certificate_first=False) \
        if compare_off else None
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        c, emit_s, build_s, size = _emit_structured(py, "cartpole_st", tmp)
        c_off = _emit_structured(off_py, "cartpole_off", tmp)[0] if off_py is not None else None
        x_off = x0.copy()
        off_rec: dict[str, list] = {"py": [], "c": [], "skipped": [], "fail_py": [],
                                   "fail_c": [], "du": [], "dx": [], "du_c": [], "its": []}
        inside_off = True
        x, x_sqp = x0.copy(), x0.copy()
        t_py, t_c, t_sqp, its, skipped = [], [], [], [], []
        fail_py = fail_c = fail_sqp = mismatch = 0
        diff, inside, inside_sqp = 0.0, True, True
        for k in range(steps):
            u_p = proposal(x, k)
            start = time.perf_counter()
            u, info = py.step(x, u_p)
            t_py.append(time.perf_counter() - start)
            start = time.perf_counter()
            u_c, info_c = c.step(x, u_p)
            t_c.append(time.perf_counter() - start)
            its.append(_iterations(info))
            skipped.append(bool(info.values.get("certificate_first")))
            fail_py += _failure(info)
            fail_c += _failure(info_c)
            mismatch += (info.status, info.fallback) != (info_c.status, info_c.fallback)
            diff = max(diff, float(np.max(np.abs(u_c - u))))
            x = d.system.step(x, u)
            inside = inside and bool(np.all(np.abs(x) <= d.X.h[:4] + 1e-9))
            if sqp is not None:
                start = time.perf_counter()
                u_s, info_s = sqp.step(x_sqp, proposal(x_sqp, k))
                t_sqp.append(time.perf_counter() - start)
                fail_sqp += _failure(info_s)
                x_sqp = d.system.step(x_sqp, u_s)
                inside_sqp = inside_sqp and bool(np.all(np.abs(x_sqp) <= d.X.h[:4] + 1e-9))
            if off_py is not None:
                u_pc = proposal(x_off, k)
                start = time.perf_counter()
                u_f, info_f = off_py.step(x_off, u_pc)
                off_rec["py"].append(time.perf_counter() - start)
                start = time.perf_counter()
                u_fc, info_fc = c_off.step(x_off, u_pc)
                off_rec["c"].append(time.perf_counter() - start)
                off_rec["skipped"].append(bool(info_f.values.get("certificate_first")))
                off_rec["fail_py"].append(_failure(info_f))
                off_rec["fail_c"].append(_failure(info_fc) or (info_f.status, info_f.fallback)
                                        != (info_fc.status, info_fc.fallback))
                off_rec["du"].append(float(np.max(np.abs(u_f - u))))
                off_rec["du_c"].append(float(np.max(np.abs(u_fc - u_f))))
                off_rec["its"].append(_iterations(info_f))
                x_off = d.system.step(x_off, u_f)
                off_rec["dx"].append(float(np.max(np.abs(x_off - x))))
                inside_off = inside_off and bool(np.all(np.abs(x_off) <= d.X.h[:4] + 1e-9))
    its = np.asarray(its)
    row = _loop_row(f"cartpole pcbf step, Python structured-ip ({steps} steps)", t_py,
                    fail_py, inside)
    row.update(**slack_iteration_stats(its, skipped),
               filter_iters_median=float(np.median(its[:, 1])),
               filter_iters_max=int(its[:, 1].max()))
    rows.append(row)
    row = _loop_row(f"cartpole pcbf step, C structured-ip via ctypes ({steps} steps)", t_c,
                    fail_c, inside)
    row.update(max_du_vs_python=float(f"{diff:.3g}"), status_mismatches=mismatch)
    rows.append(row)
    if sqp is not None:
        rows.append(_loop_row(f"cartpole pcbf step, Python fast-sqp ({steps} steps)", t_sqp,
                              fail_sqp, inside_sqp))
    if off_py is not None:
        its_off = np.asarray(off_rec["its"])
        common = {"max_du_vs_default_loop": float(f"{max(off_rec['du']):.3g}"),
                  "max_dx_vs_default_loop": float(f"{max(off_rec['dx']):.3g}")}
        row = _loop_row(f"cartpole pcbf step, Python structured-ip certificate_first=False "
                        f"({steps} steps)", off_rec["py"], sum(off_rec["fail_py"]), inside_off)
        row.update(common, **slack_iteration_stats(its_off, off_rec["skipped"]),
                   filter_iters_median=float(np.median(its_off[:, 1])))
        rows.append(row)
        row = _loop_row(f"cartpole pcbf step, C structured-ip certificate_first=False via ctypes "
                        f"({steps} steps)", off_rec["c"], sum(off_rec["fail_c"]), inside_off)
        row.update(common, skipped_slack_solves=int(sum(off_rec["skipped"])),
                   max_du_vs_python=float(f"{max(off_rec['du_c']):.3g}"))
        rows.append(row)
    rows.append({"name": "cartpole pcbf structured-ip C module", "emit_s": round(emit_s, 1),
                 "build_s": round(build_s, 1), "source_bytes": size,
                 "note": "cc -O3 -Werror, linked to libfatrop/libblasfeo/libipopt"})
    return rows


#: fatrop options tried as warm-start settings by :func:`run_warm_starts` (libfatrop 1.1.8 has
#: no ``warm_start_init_point``; its option registry has ``mu_init``, ``bound_push``,
#: ``bound_frac``)
WARM_VARIANTS: dict[str, dict] = {
    "mu_init 1e-3": {"mu_init": 1e-3},
    "mu_init 1e-4, bound_push/frac 1e-4": {"mu_init": 1e-4, "bound_push": 1e-4,
                                           "bound_frac": 1e-4},
    "mu_init 1e-6, bound_push/frac 1e-8": {"mu_init": 1e-6, "bound_push": 1e-8,
                                           "bound_frac": 1e-8},
}


class _ColdStarts(PCBFSafetyFilter):
    """Every solve from the declared initial point (no warm start)."""

    def _slack_start(self, x: np.ndarray) -> None:
        return None

    def _step(self, x: np.ndarray, u_p: np.ndarray) -> tuple:
        self._last_filter = None
        return super()._step(x, u_p)


def run_warm_starts(steps: int = 40) -> list[dict]:
    """fatrop's iterations and step times on the closed loop under warm-start rules, from
    Python, interleaved step by step (each rule its own loop): the last solution (the
    default, what the emitted C does), the shifted last plan (``warm_start="shifted"``),
    cold starts, and the default rule with the fatrop options of :data:`WARM_VARIANTS`
    (first attempt only; the cold retry keeps the defaults). fatrop takes no dual warm
    start through CasADi (its OCP interface asks only for initial ``x_k``/``u_k``)."""
    from balustrade.backends import Target

    d = cartpole_design()
    x0, proposal = cartpole_scenario()
    problems = cartpole_problems("structured-ip", design=d)
    off = {"certificate_first": False}  # every (2.24) solved: its iterations are measured
    loops = {"last solution (default)": PCBFSafetyFilter(*problems, d.U, **off),
             "shifted plan": PCBFSafetyFilter(*problems, d.U, warm_start="shifted", **off),
             "cold": _ColdStarts(*problems, d.U, **off)}
    base = {"print_level": 0, "max_iter": 300}
    for label, extra in WARM_VARIANTS.items():
        target = Target("casadi", "fatrop", {"fatrop": {**base, **extra}},
                        retries=(("fatrop", {"fatrop": base}), ("ipopt", {})), name=label)
        loops[label] = PCBFSafetyFilter(*cartpole_problems(target, design=d), d.U, **off)
    state = {k: x0.copy() for k in loops}
    rec: dict[str, list] = {k: [] for k in loops}
    for k in range(steps):
        for label, filt in loops.items():
            x = state[label]
            start = time.perf_counter()
            u, info = filt.step(x, proposal(x, k))
            rec[label].append((time.perf_counter() - start, _iterations(info), _failure(info),
                               float(u[0])))
            state[label] = d.system.step(x, u)
    u_ref = np.array([r[3] for r in rec["last solution (default)"]])
    rows = []
    for label, r in rec.items():
        its = np.array([x[1] for x in r])
        du = float(np.max(np.abs(np.array([x[3] for x in r]) - u_ref)))
        rows.append({"name": f"warm start: {label} ({steps} steps)",
                     "median_ms": round(1e3 * float(np.median([x[0] for x in r])), 1),
                     "worst_ms": round(1e3 * max(x[0] for x in r), 1),
                     "slack_iters_median": float(np.median(its[:, 0])),
                     "slack_iters_max": int(its[:, 0].max()),
                     "filter_iters_median": float(np.median(its[:, 1])),
                     "filter_iters_max": int(its[:, 1].max()),
                     "failures": sum(x[2] for x in r),
                     "max_du_vs_default": float(f"{du:.3g}")})
    return rows


if __name__ == "__main__":  # pragma: no cover
    import sys

    args = sys.argv[1:]
    steps = next((int(a) for a in args if a.isdigit()), 100)
    if "structured" in args:
        rows = run_structured(steps, with_sqp="--sqp" in args,
                              compare_off="--no-certificate-first" in args)
    elif "warm" in args:
        rows = run_warm_starts(next((int(a) for a in args if a.isdigit()), 40))
    else:
        rows = run()
    for row in rows:
        print(row)
