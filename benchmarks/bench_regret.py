"""Regret SDPs of the rocket (Section 3.8): structured synthesis against a dense transcription.

Each case runs in a fresh subprocess so that its peak resident memory can be reported
(``peak_mem_mb`` = the child's max RSS, Python and imports included, about 100 MB).

* banded (ours, the default): :func:`balustrade.control.regret_synthesis.generalized_regret`
  (the problem :func:`balustrade.problems.regret.generalized_regret_problem`) — causal
  variables only, Φ_x eliminated, cost compressed by the square-root factor, the LMI in banded
  coordinates (backends/lmi_banded.py) decomposed by Clarabel;
* split / single: the same compressed LMI with our chordal split, or as one cone in the
  original coordinates (``lmi="split"`` / ``lmi="single"``), reported in their own rows;
* dense: a direct transcription of (3.28) — dense Φ with (3.14) and causality as equality
  constraints, C^{1/2} and 𝒪 blocks in one LMI of size 1 + pT + (n+m)(T+1).

These rows are without the constraints (3.41), so that both sides are the same SDP; each row
records the relative difference of the optimal levels, ``ok`` and the form actually used
(``lmi_used``: a banded solve that is not ok is re-solved with lmi="split", and its time
includes both). Quick: T = 5. Full: T = 10 (all forms
and dense), T = 25 (banded and single; the dense T = 25 transcription, ≈ 100 s and ≈ 9 GB on
the machine of the issue and killed at 24 GB here, only with BALUSTRADE_BENCH_DENSE_T25=1 and
enough free memory), and the six Table 3.1 syntheses at T = 25 *with* (3.41), banded (their
baseline is the chordal split of the same problem, measured in the same run only with
BALUSTRADE_BENCH_SPLIT_T25=1: 6–10 min each).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

_CHILD = r"""
import json, resource, sys, time
import numpy as np
from balustrade.models.rocket import RocketRegretSetup
from balustrade.backends import resolve_target
from balustrade.backends.regret_dense import dense_generalized_regret
from balustrade.control.regret_synthesis import generalized_regret
from balustrade.problems.regret import LTVSystem, build_operators

T, W, kind = int(sys.argv[1]), sys.argv[2], sys.argv[3]
s = RocketRegretSetup(T=T)
ops = build_operators(LTVSystem.create(s.A, s.B, T))
x0, om = s.x0, s.omega
# both sides solved to the same tight tolerances, so that the levels can agree to 1e-6
TOL = resolve_target("sdp", options={"tol_gap_rel": 1e-10, "tol_gap_abs": 1e-10,
                                           "tol_feas": 1e-10})
t0 = time.perf_counter()
if kind.startswith("table:"):
    from balustrade.reproduce.rocket_regret import synthesis_makers
    form = kind.split(":")[2]
    res = synthesis_makers(s, lmi=form)[0][kind.split(":")[1]]()
    level, status, ok, used = res.level, res.status, res.ok, res.info.get("lmi")
elif kind in ("banded", "split", "single"):
    res = generalized_regret(ops, x0, om, W, lmi=kind, target=TOL)
    level, status, ok, used = res.level, res.status, res.ok, res.info.get("lmi")
else:
    Wm = np.eye(ops.nd) if W == "I" else ops.O
    status, level = dense_generalized_regret(ops, x0, om, Wm, target=TOL)
    ok, used = status == "optimal", "dense"
elapsed = time.perf_counter() - t0
rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps({"time": elapsed, "level": None if level is None else float(level),
                  "status": status, "ok": ok, "lmi_used": used, "rss_mb": rss}))
"""


def _run_case(T: int, W: str, kind: str) -> dict:
    out = subprocess.run([sys.executable, "-c", _CHILD, str(T), W, kind],
                         capture_output=True, text=True, check=False)
    if out.returncode != 0:
        return {"time": float("nan"), "level": None, "status": f"error: {out.stderr[-300:]}",
                "rss_mb": float("nan")}
    return json.loads(out.stdout.strip().splitlines()[-1])


def _mem_available_gb() -> float:
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable"):
                    return int(line.split()[1]) / 1024**2
    except OSError:
        pass
    return 0.0


def _row(T: int, W: str, ours: dict, dense: dict | None, variant: str = "") -> dict:
    label = "dynamic regret" if W == "I" else "competitive ratio"
    row = {"name": f"rocket (3.28) {label} T={T}{variant}", "median_s": ours["time"],
           "peak_mem_mb": round(ours["rss_mb"], 1), "level": ours["level"],
           "status": ours["status"], "ok": ours.get("ok"), "lmi_used": ours.get("lmi_used")}
    if dense is not None:
        row.update({"baseline": "dense (3.28)", "ratio": dense["time"] / ours["time"],
                    "baseline_s": dense["time"], "baseline_peak_mem_mb": round(dense["rss_mb"], 1),
                    "baseline_status": dense["status"]})
        if ours["level"] is not None and dense["level"] is not None:
            row["level_rel_diff"] = abs(ours["level"] - dense["level"]) / abs(dense["level"])
    return row


def run(quick: bool) -> list[dict]:
    rows = []
    cases = [(5, True, ("split", "single"))] if quick else [
        (10, True, ("split", "single")), (25, False, ("single",))]
    for T, with_dense, variants in cases:
        for W in ("I", "O"):
            ours = _run_case(T, W, "banded")
            dense_wanted = with_dense or (
                T == 25 and os.environ.get("BALUSTRADE_BENCH_DENSE_T25") == "1"
                and _mem_available_gb() > 14)
            dense = _run_case(T, W, "dense") if dense_wanted else None
            rows.append(_row(T, W, ours, dense))
            for form in variants:
                other = _run_case(T, W, form)
                rows.append(_row(T, W, other, dense, f" (lmi={form})"))
    if not quick:
        with_split = os.environ.get("BALUSTRADE_BENCH_SPLIT_T25") == "1"
        for name in ("SH2", "SH∞", "SDR", "SCR", "SDRW", "SCRW"):
            ours = _run_case(25, "-", f"table:{name}:banded")
            row = {"name": f"rocket Table 3.1 {name} T=25 with (3.41)", "median_s": ours["time"],
                   "peak_mem_mb": round(ours["rss_mb"], 1), "level": ours["level"],
                   "status": ours["status"], "ok": ours.get("ok"),
                   "lmi_used": ours.get("lmi_used"), "goal_s": 10.0, "goal_mem_mb": 2048}
            if with_split and name != "SH2":
                base = _run_case(25, "-", f"table:{name}:split")
                row.update({"baseline": "chordal split (lmi='split')",
                            "ratio": base["time"] / ours["time"], "baseline_s": base["time"],
                            "baseline_peak_mem_mb": round(base["rss_mb"], 1)})
            rows.append(row)
    return rows
