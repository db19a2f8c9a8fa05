"""Algorithm 7.5 on the obstacle car (Sec. 8.3): where the C step's time goes, per path and
per part, inside C and as seen from Python (docs/obstacles.md, "Timing").

    PYTHONPATH=$PWD python benchmarks/obstacles_c_step.py [build_dir] [repeats] [extra flags...]

1. Records the (x, u_p) of the Python closed loops of ``reproduce obstacles --quick`` (the
   committed network, ρ = 0.5, the naive MPC, 5 starts × 70 steps).
2. Emits the filter (:func:`~balustrade.codegen.emit_approximate`, name ``obs``) twice:
   ``casadi`` (ĥ as CasADi's generated scalar code) and ``loops`` (``network=``: ĥ from the
   weights, bal/approx_net.c), and compiles each with the emitter's flags
   (:data:`~balustrade.codegen.build.BASE_FLAGS`, ``THREAD_FLAGS``, plus any extra flags
   given, e.g. ``-march=native``, which is not portable): the library and the C driver
   ``obstacles_c_step.c`` (the CasADi part, ~1–4 min each, is cached by hash).
3. Replays every recorded step in C (``clock_gettime``), the two variants taking turns
   (twice): the median per path, warm (the step repeated) and cold (64 MB written between
   calls, as when other work runs between control steps), and the parts of a solved step;
   checks that both chose the same inputs, and that the library (through ctypes) chose the
   driver's: a difference above :data:`SAME_TOL` raises after the table is printed.
4. Replays them through the Python filter and both C libraries
   (:class:`~balustrade.codegen.CApproximatePCBFFilter`, ctypes) taking turns: the medians
   a closed loop sees.
"""

from __future__ import annotations

import dataclasses
import hashlib
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from balustrade.codegen import CApproximatePCBFFilter, emit_approximate
from balustrade.codegen.build import BASE_FLAGS, THREAD_FLAGS, find_compiler
from balustrade.control.approximate import ApproximatePCBFFilter
from balustrade.learn.export import to_casadi
from balustrade.learn.train import MLPModel
from balustrade.models.obstacle_car import obstacle_car, obstacle_setup
from balustrade.reproduce import obstacles as O

DRIVER = Path(__file__).with_name("obstacles_c_step.c")


def make_filter() -> ApproximatePCBFFilter:
    """The filter of ``reproduce obstacles`` (committed network, ρ = 0.5, ``fast-sqp``)."""
    s, net = obstacle_setup(), MLPModel.load(O.NET)
    return ApproximatePCBFFilter(obstacle_car(), s.U, to_casadi(net), rho=O.RHO,
                                 target=O.FILTER_TARGET, network=net)


def record(filt: ApproximatePCBFFilter) -> tuple[np.ndarray, np.ndarray]:
    """The states and proposals of the Python closed loops (5 starts × 70 steps)."""
    runs = O.closed_loops(filt, O.NaiveMPC())
    X = np.vstack([r["states"][:len(r["proposed"])] for r in runs])
    return X, np.vstack([r["proposed"] for r in runs])


def _run(cmd: list[str]) -> None:
    subprocess.run(cmd, check=True, capture_output=True, text=True)


def build_variant(spec: object, out: Path, flags: tuple[str, ...]) -> tuple[Path, Path]:
    """Emit ``obs`` from ``spec`` into ``out``; build ``libobs.so`` and the driver (the
    CasADi object cached by the hash of its source and the flags)."""
    emit_approximate(spec, "obs", out)
    cc, all_flags = find_compiler(), [*BASE_FLAGS, *THREAD_FLAGS, *flags]
    tag = hashlib.sha256(" ".join(all_flags).encode()
                         + (out / "obs_casadi.c").read_bytes()).hexdigest()[:16]
    obj = out / f"obs_casadi-{tag}.o"
    if not obj.exists():
        _run([cc, *all_flags, "-c", "-o", str(obj), str(out / "obs_casadi.c")])
    lib, drv = out / "libobs.so", out / "driver"
    _run([cc, *all_flags, "-shared", "-o", str(lib), str(out / "obs.c"), str(obj), "-lm"])
    (out / "driver.c").write_text(DRIVER.read_text())
    _run([cc, *all_flags, "-o", str(drv), str(out / "driver.c"), str(obj), "-lm"])
    return lib, drv


def in_c(drv: Path, steps: Path, repeats: int) -> dict:
    """Run the driver on the recorded steps; its medians (µs) and chosen inputs."""
    text = subprocess.run([str(drv), str(steps), str(repeats)], check=True,
                          capture_output=True, text=True).stdout
    res: dict = {"paths": {}, "parts": {}, "u": []}
    for line in text.splitlines():
        w = line.split()
        if w[0] == "u":
            res["u"].append([float(w[2]), float(w[3])])
        elif w[0] == "path":
            res["paths"][(w[1], w[2])] = (int(w[3]), float(w[4]))
        elif w[0] == "part":
            res["parts"][w[1]] = (int(w[2]), float(w[3]))
        elif w[0] == "candidates":
            res["candidates"] = int(w[1])
    res["u"] = np.asarray(res["u"])
    return res


def through_ctypes(ctls: dict, X: np.ndarray, P: np.ndarray, repeats: int) -> dict:
    """The controllers taking turns on every recorded step: medians (µs) per controller
    and path, as ``StepInfo.solve_time`` reports them, and each one's last inputs."""
    times: dict = {}
    inputs: dict = {k: [] for k in ctls}
    for x, p in zip(X, P):
        last = {}
        for _ in range(repeats):
            for key, ctl in ctls.items():
                last[key], info = ctl.step(x, p)
                path = O.path_of(info.status, info.fallback)
                times.setdefault((key, path), []).append(info.solve_time)
        for key in ctls:
            inputs[key].append(last[key])
    med = {k: (len(v) // repeats, 1e6 * float(np.median(v))) for k, v in times.items()}
    return {"median_us": med, "u": {k: np.asarray(v) for k, v in inputs.items()}}


#: the largest input difference between the C variants (and the library and the driver)
#: accepted: the same decisions (tests/test_codegen_approximate.py: bit for bit without
#: extra flags; flags such as -march=native may contract operations differently)
SAME_TOL = 1e-6

PATHS = {"certified": "certified", "kept": "decrease_solved_proposal_kept",
         "both": "both_solves"}


def main(build_dir: str | None = None, repeats: int = 7, flags: tuple[str, ...] = ()) -> dict:
    out = Path(build_dir or Path(tempfile.gettempdir()) / "balustrade-obstacles-c-step")
    out.mkdir(parents=True, exist_ok=True)
    filt = make_filter()
    X, P = record(filt)
    steps = out / "steps.txt"
    np.savetxt(steps, np.hstack([X, P]), fmt="%.17g")
    spec = filt.deployment_spec()
    specs = {"casadi": dataclasses.replace(spec, network=None), "loops": spec}
    built = {k: build_variant(v, out / k, flags) for k, v in specs.items()}
    runs: dict = {k: [] for k in specs}
    for _ in range(2):  # the variants take turns
        for k, (_, drv) in built.items():
            runs[k].append(in_c(drv, steps, repeats))
    ctls = {"python": filt, **{k: CApproximatePCBFFilter(lib) for k, (lib, _) in built.items()}}
    via = through_ctypes(ctls, X, P, max(1, repeats // 2))
    same = float(np.max(np.abs(runs["casadi"][0]["u"] - runs["loops"][0]["u"])))
    lib_same = float(np.max(np.abs(via["u"]["casadi"] - runs["casadi"][0]["u"])))
    print(f"{len(X)} recorded steps; flags {' '.join((*BASE_FLAGS, *THREAD_FLAGS, *flags))}; "
          "inputs: "
          f"loops vs casadi max difference {same:.3g}, library vs driver {lib_same:.3g}")
    print("path (n)               | variant | C warm (us) | C cold (us) | C via ctypes (us) "
          "| Python (us)")
    for key, label in PATHS.items():
        pt = via["median_us"].get(("python", label), (0, float("nan")))[1]
        for k in specs:
            n = runs[k][0]["paths"][("warm", key)][0]
            warm = np.mean([r["paths"][("warm", key)][1] for r in runs[k]])
            cold = np.mean([r["paths"][("cold", key)][1] for r in runs[k]])
            ct = via["median_us"].get((k, label), (0, float("nan")))[1]
            print(f"{label[:18]:18s}({n:3d}) | {k:7s} | {warm:11.1f} | {cold:11.1f} | "
                  f"{ct:17.1f} | {pt:11.1f}")
    for k in specs:
        parts = runs[k][0]["parts"]
        print(f"parts ({k}, C, warm): one h^(f(x, u)) {parts['h_next'][1]:.2f} us; h^(x) + "
              f"screening of {runs[k][0]['candidates']} candidates + 1 local (7.6) "
              f"{parts['screening'][1]:.1f} us; one (7.6) solve {parts['dec_solve'][1]:.1f} "
              f"us; one (7.5) solve {parts['filter_solve'][1]:.1f} us")
    if not (same <= SAME_TOL and lib_same <= SAME_TOL):
        raise RuntimeError(f"obstacles_c_step: the C variants chose different inputs (loops "
                           f"vs casadi {same:.3g}, library vs driver {lib_same:.3g}; "
                           f"tolerance {SAME_TOL:g})")
    return {"c": runs, "ctypes": via}


if __name__ == "__main__":
    a = sys.argv[1:]
    main(a[0] if a else None, int(a[1]) if len(a) > 1 else 7, tuple(a[2:]))
