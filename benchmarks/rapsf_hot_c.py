"""The emitted hot-started Algorithm 4.1 step (``bal/rapsf_hot.c``, docs/deploy_c.md
"Session 15") against Python's default RAPSF, same closed loop, same run::

    PYTHONPATH=$PWD python -m benchmarks.rapsf_hot_c [masses] [steps] [sqp]

Two closed loops of the ``reproduce msd-adaptive`` design (box update, §4.7 chain, ``θ*``
and disturbances of seed 0; :class:`benchmarks.bench_rapsf.Loop`): ``RAPSF(...)`` on its
default target, and :class:`~balustrade.codegen.CRAPSF` on the C emitted from it, taking
turns every step (which goes first alternates; the first, compiling step not timed). Per
step: wall and CPU time (``time.process_time``) of the Python step, of the
``CRAPSF.step`` (the Python box update + the C call) and of the C call alone (ctypes).
The C steps' arguments are recorded and replayed by the C harness
``benchmarks/rapsf_hot_c.c`` (built against the same module), which times each call with
``clock_gettime`` (monotonic and process CPU clocks) and whose inputs must equal the
``CRAPSF`` ones (the same calls from the same start). ``sqp``: a third loop, the C emitted
from ``target="convex-qp"`` (the SQP with the solver started cold, the C of Algorithm 4.1
before session 15; its build takes minutes), interleaved with the two. Prints medians,
p90s and worst.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from balustrade.codegen import CRAPSF, build, build_executable, emit_rapsf
from balustrade.codegen.emit_rapsf import link_flags
from balustrade.reproduce import msd_adaptive
from benchmarks.bench_rapsf import Loop

HERE = Path(__file__).resolve().parent


def _q(v: np.ndarray) -> str:
    return f"{np.median(v):.3f} / {np.quantile(v, 0.9):.3f} / {np.max(v):.3f}"


def _sqp_c(d: dict, tmp: Path) -> CRAPSF:
    """The C of ``target="convex-qp"`` (bal/rapsf.c) for the same design."""
    ctrl = msd_adaptive.adaptive_controller(d, target="convex-qp")
    em = emit_rapsf(ctrl, "rq", tmp / "sqp")
    lib = build(em.out_dir, "rq", extra_flags=link_flags(em.libraries))
    return CRAPSF(lib, host=ctrl)


def run(masses: int = 3, steps: int = 150, sqp: bool = False) -> dict:
    d = msd_adaptive.design(masses)
    ctrl = msd_adaptive.adaptive_controller(d)
    tmp = Path(tempfile.mkdtemp(prefix="rapsf_hot_c_"))
    em = emit_rapsf(ctrl, "rh", tmp)
    flags = link_flags(em.libraries)
    c = CRAPSF(build(tmp, "rh", werror=True, extra_flags=flags), host=ctrl)
    (tmp / "main.c").write_text((HERE / "rapsf_hot_c.c").read_text())
    exe = build_executable(tmp, "main.c", extra_flags=flags)
    calls: list[tuple] = []
    c_times: list[tuple[float, float]] = []
    raw = c.step_raw

    def timed_raw(x, u_p, falsified=False):
        calls.append((np.array(x, float), np.array(u_p, float), c._theta.copy(),
                      c._s.copy(), float(bool(falsified))))
        c0, t0 = time.process_time(), time.perf_counter()
        out = raw(x, u_p, falsified)
        c_times.append((time.perf_counter() - t0, time.process_time() - c0))
        return out
    c.step_raw = timed_raw

    loops = {"python": Loop(d, ctrl.step, steps), "c": Loop(d, c.step, steps)}
    if sqp:
        loops["sqp"] = Loop(d, _sqp_c(d, tmp).step, steps)
    cpu = {k: [] for k in loops}
    for k in range(steps):
        for label in (list(loops) if k % 2 else list(loops)[::-1]):
            c0 = time.process_time()
            loops[label](k)
            cpu[label].append(time.process_time() - c0)
    du = float(np.max(np.abs(np.array(loops["python"].applied) - np.array(loops["c"].applied))))
    rec = tmp / "calls.bin"
    with open(rec, "wb") as f:
        np.array([len(calls), calls[0][0].size, calls[0][1].size, calls[0][2].size,
                  calls[0][3].size], dtype=np.int64).tofile(f)
        for x, up, th, s, fa in calls:
            np.concatenate([x, up, th, s, [fa]]).tofile(f)
    out = tmp / "harness.bin"
    subprocess.run([str(exe), str(rec), str(out)], check=True, timeout=600)
    nu = calls[0][1].size
    h = np.fromfile(out).reshape(len(calls), 3 + nu)
    du_h = float(np.max(np.abs(h[:, 3:] - np.array(loops["c"].applied))))
    ms = 1e3
    extra = {} if not sqp else {
        "sqp_wall": np.array(loops["sqp"].times[1:]) * ms,
        "sqp_cpu": np.array(cpu["sqp"][1:]) * ms,
        "max_du_sqp": float(np.max(np.abs(np.array(loops["sqp"].applied)
                                          - np.array(loops["python"].applied))))}
    return {**extra,"masses": masses, "steps": steps, "qp_sizes": em.manifest["qp_sizes"],
            "python_wall": np.array(loops["python"].times[1:]) * ms,
            "python_cpu": np.array(cpu["python"][1:]) * ms,
            "crapsf_wall": np.array(loops["c"].times[1:]) * ms,
            "crapsf_cpu": np.array(cpu["c"][1:]) * ms,
            "ccall_wall": np.array([t for t, _ in c_times[1:]]) * ms,
            "ccall_cpu": np.array([t for _, t in c_times[1:]]) * ms,
            "harness_wall": h[1:, 0], "harness_cpu": h[1:, 1],
            "max_du": du, "max_du_harness": du_h,
            "fallbacks": {k: v.fallbacks for k, v in loops.items()},
            "load": Path("/proc/loadavg").read_text().split()[:3]}


def main(argv: list[str]) -> None:
    masses = int(argv[0]) if argv else 3
    steps = int(argv[1]) if len(argv) > 1 else 150
    r = run(masses, steps, len(argv) > 2 and argv[2] == "sqp")
    sizes = ", ".join(f"{k} {m} x {n}" for k, (m, n) in r["qp_sizes"].items())
    print(f"{masses} masses, {steps} steps (first not timed), lowered (4.5) in C: {sizes}; "
          f"load average {' '.join(r['load'])}")
    print("per step, median / p90 / worst [ms]:           wall                  CPU")
    for key, label in (("python", "Python RAPSF, default target"),
                       ("crapsf", "CRAPSF.step (box update + C)"),
                       ("ccall", "the C call through ctypes"),
                       ("harness", "the C call in the C harness"),
                       ("sqp", "CRAPSF.step, C of convex-qp")):
        if key + "_wall" not in r:
            continue
        print(f"  {label:<32} {_q(r[key + '_wall']):>22}  {_q(r[key + '_cpu']):>22}")
    print(f"max |u_C - u_Python| {r['max_du']:.2e}; harness vs CRAPSF {r['max_du_harness']:.2e};"
          f" loop fallbacks {r['fallbacks']}")
    if "max_du_sqp" in r:
        print(f"max |u_convex-qp C - u_Python| {r['max_du_sqp']:.2e} (own states)")


if __name__ == "__main__":
    main(sys.argv[1:])
