"""The expanded and the compact CasADi lowering (issue #14 §3) on the PCBF pair
(2.24)+(2.23) of the pendulum and the cart-pole (RK4, N = 20), ``fast-sqp`` target.

Per system and lowering (``"expanded"``: one SX graph, derivatives written out per stage;
``"compact"``: MX with the dynamics one stage function mapped over the horizon,
:func:`~balustrade.backends.passes.casadi_nlp.compact_nlp`):

* the emitted C (:func:`~balustrade.codegen.emit_pcbf` with ``EMIT_LOWERING`` set): source
  bytes and build time (``cc -O3 -Werror``, :func:`~balustrade.codegen.build`);
* the step of the C library through ctypes and of the Python filter compiled with that
  lowering (target option ``"lowering"``), median and worst over the same states,
  interleaved state by state (A, B, A, B, …);
* ``max |u − u_Py|`` against the Python filter on the default (expanded) lowering, over
  the states where both report ``ok`` (``compared`` of them). Every step starts cold
  (``reset()``), so the step times are cold-start solves, not a warm closed loop.

Times are taken on a shared machine (under load); compare ratios within one run.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from balustrade.backends import PRESETS
from balustrade.codegen import CPCBFSafetyFilter, build, emit_pcbf
from balustrade.codegen import emit as emit_module
from balustrade.control import PCBFSafetyFilter

LOWERINGS = ("expanded", "compact")


def _pendulum(lowering: str) -> tuple[PCBFSafetyFilter, np.ndarray]:
    from balustrade.examples.pendulum import pendulum_terminal_cbf
    from balustrade.models.pendulum import pendulum, pendulum_setup

    system, s = pendulum(), pendulum_setup()
    tgt = PRESETS["fast-sqp"].with_options(lowering=lowering)
    filt = PCBFSafetyFilter.build(system, s.X, s.U, pendulum_terminal_cbf(), s.N, s.deltas,
                                  s.alpha_f, slack_norm=1, target=tgt)
    rng = np.random.default_rng(0)
    return filt, rng.uniform([-0.5, -1.5], [0.5, 1.5], size=(200, 2))


def _cartpole(lowering: str) -> tuple[PCBFSafetyFilter, np.ndarray]:
    from balustrade.examples.cartpole import cartpole_design, cartpole_problems

    d = cartpole_design()
    tgt = PRESETS["fast-sqp"].with_options(lowering=lowering)
    filt = PCBFSafetyFilter(*cartpole_problems(tgt, design=d), d.U)
    return filt, d.X.sample(40, np.random.default_rng(0)) * 0.5


def _proposal(system: str, x: np.ndarray) -> np.ndarray:
    if system == "pendulum":
        return np.array([2.0])
    from balustrade.examples.cartpole import destabilizing_proposal

    return destabilizing_proposal(x, 0)


def run(quick: bool = False, systems: tuple[str, ...] = ("pendulum", "cartpole")) -> list[dict]:
    rows = []
    makers = {"pendulum": _pendulum, "cartpole": _cartpole}
    for system in systems:
        py, c, meta = {}, {}, {}
        with tempfile.TemporaryDirectory() as tmp:
            for lowering in LOWERINGS:
                py[lowering], states = makers[system](lowering)
                old = emit_module.EMIT_LOWERING
                emit_module.EMIT_LOWERING = lowering
                try:
                    out = Path(tmp) / lowering
                    emitted = emit_pcbf(py["expanded"], f"{system}_{lowering}", out)
                finally:
                    emit_module.EMIT_LOWERING = old
                size = sum(p.stat().st_size for p in emitted.sources + emitted.headers)
                t0 = time.perf_counter()
                lib = build(out, emitted.name, werror=True)
                meta[lowering] = {"source_bytes": size,
                                  "build_s": round(time.perf_counter() - t0, 2)}
                c[lowering] = CPCBFSafetyFilter(lib)
            if quick:
                states = states[:10]
            times = {(k, low): [] for k in ("C", "Py") for low in LOWERINGS}
            diff = {(k, low): 0.0 for k in ("C", "Py") for low in LOWERINGS}
            compared = {(k, low): 0 for k in ("C", "Py") for low in LOWERINGS}
            for x in states:
                u_p = _proposal(system, x)
                ref = None
                for low in LOWERINGS:  # interleaved: Py exp, C exp, Py compact, C compact
                    for kind, filt in (("Py", py[low]), ("C", c[low])):
                        filt.reset()
                        t = time.perf_counter()
                        u, info = filt.step(x, u_p)
                        times[kind, low].append(time.perf_counter() - t)
                        if kind == "Py" and low == "expanded":
                            ref = u if info.status == "ok" else None
                        elif ref is not None and info.status == "ok":
                            compared[kind, low] += 1
                            diff[kind, low] = max(diff[kind, low],
                                                  float(np.max(np.abs(u - ref))))
        for low in LOWERINGS:
            rows.append({"name": f"{system} pcbf C module, {low}",
                         "median_s": meta[low]["build_s"], **meta[low],
                         "note": "median_s = build time (cc -O3 -Werror)"})
            for kind in ("Py", "C"):
                t = times[kind, low]
                row = {"name": f"{system} pcbf step {kind}, {low} ({len(t)} states)",
                       "median_s": float(np.median(t)), "worst_ms": round(1e3 * max(t), 2)}
                if (kind, low) != ("Py", "expanded"):
                    row["max_du_vs_py_expanded"] = float(f"{diff[kind, low]:.3g}")
                    row["compared"] = compared[kind, low]
                rows.append(row)
    return rows


if __name__ == "__main__":  # pragma: no cover
    import sys

    for row in run(quick="--quick" in sys.argv,
                   systems=tuple(a for a in sys.argv[1:] if not a.startswith("-"))
                   or ("pendulum", "cartpole")):
        print(row)
