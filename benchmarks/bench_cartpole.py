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
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from balustrade.codegen import CPCBFSafetyFilter, build, emit_pcbf
from balustrade.control import PCBFSafetyFilter
from balustrade.examples.cartpole import cartpole_design, cartpole_problems, cartpole_scenario


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


if __name__ == "__main__":  # pragma: no cover
    for row in run():
        print(row)
