"""Section 6.5 / Figures 6.1 and 6.2: space rendezvous, robust PCBF (Algorithm 5.2) vs the
multiobjective robust PCBF (Algorithm 6.4) for several ``ρ``, with and without disturbance.

Model and units: :mod:`balustrade.models.rendezvous` (CWH, exact ZOH, ``T_s = 1``, ``n = 0.01``,
normalized units). Error set: ellipsoidal RPI set and ``K`` by the SDP of SPEC §1.11 with the
disturbance entering the velocities; terminal CBF: SDP (6.17) on ``X ⊖ E``, ``U ⊖ K E`` with the
input LMI on ``(U ⊖ KE)/√2`` so that ``γ_f >= 1`` (:func:`terminal_cbf_with_domain`). Primary
objective ``J = Σ_i ‖v_i‖₁`` (SPEC §3.4), slack norm ``ℓ1``, disturbance i.i.d. uniform in ``W``
(seed 0), proposal ignored (``J`` does not use ``u_p``). Fuel is ``Σ_k ‖u_k‖₁`` of the applied
inputs. Per-step time is the solver time of the step's problems (two for 5.2, one for 6.4;
the extra (5.15) solve that records ``h_r`` for the plots under 6.4 is not counted).
Targets: every problem on ``fast-convex`` (the direct conic backend, the solver's own
interface, issue #14): per step at N = 200, median of 12 interleaved steps on the loaded
2-core machine, 0.22 s (5.2) and 0.20 s (6.4) vs cvxpy 0.34 s / 0.27 s and CasADi
(``long-horizon`` for 5.2, ``exact`` for 6.4, the earlier defaults) 1.20 s / 2.81 s; pass
``target="long-horizon"`` etc. for the CasADi runs. Slacks are polished afterwards
(:func:`~balustrade.control.robust_steps.polished_slacks`). Full mode runs the robust PCBF
and ``ρ ∈ {0, 0.5, 0.9}`` with disturbance and the robust PCBF and ``ρ = 0.9`` without.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from balustrade.control.multiobjective import MultiobjectivePCBFController
from balustrade.control.robust import RobustPCBFSafetyFilter
from balustrade.design.rpi import ellipsoidal_rpi
from balustrade.design.terminal_cbf import terminal_cbf_with_domain
from balustrade.dsl.error_sets import is_rpi
from balustrade.dsl.policies import AffinePolicy
from balustrade.models.rendezvous import MEAN_MOTION, TS, rendezvous, rendezvous_setup
from balustrade.problems.robust import fuel_objective
from balustrade.reproduce._plotting import figure, save

NAMES = ("rendezvous",)
THESIS = {"fuel_disturbed": {"robust": 2038, "multiobjective": 1551, "change_pct": -23.9},
          "fuel_nominal": {"robust": 1225, "multiobjective": 809, "change_pct": -34.0},
          "step_ms": {"robust": 234, "multiobjective": 148}}


def design(N: int, T: int) -> dict:
    system, s = rendezvous(), rendezvous_setup(N, T)
    error = ellipsoidal_rpi(system.A, system.B, s.W, s.X, s.U, G=system.E)
    X_E, U_E = error.tighten_state(s.X), error.tighten_input(s.U)
    cbf = terminal_cbf_with_domain(system.A, system.B, X_E, U_E, s.deltas()[-1], level=1.0)
    return {"system": system, "setup": s, "error": error, "cbf": cbf}


#: targets of Algorithm 5.2 (both problems) and Algorithm 6.4 (module docstring)
ROBUST_TARGET, MULTIOBJECTIVE_TARGET = "fast-convex", "fast-convex"


def controllers(d: dict, rhos: tuple[float, ...], target: str | None = None,
                record_h_r: bool = True) -> dict:
    """The robust PCBF and one multiobjective controller per ``ρ``; every problem on
    ``target`` when given (e.g. ``"cvxpy"``), else on the targets of the module docstring."""
    system, s, error, cbf = d["system"], d["setup"], d["error"], d["cbf"]
    robust = target or ROBUST_TARGET
    out = {"robust": RobustPCBFSafetyFilter.build(
        system, s.X, s.U, cbf, AffinePolicy(cbf.K), s.N, s.deltas(), error, s.alpha_f,
        objective=fuel_objective, target=robust, slack_target=robust)}
    for rho in rhos:
        out[f"mo_rho{rho:g}"] = MultiobjectivePCBFController.build(
            system, s.X, s.U, cbf, AffinePolicy(cbf.K), s.N, s.deltas(), error, s.alpha_f, rho=rho,
            objective=fuel_objective, target=target or MULTIOBJECTIVE_TARGET,
            record_h_r=record_h_r)
    return out


def closed_loop(controller, d: dict, disturbed: bool, seed: int = 0) -> dict:
    system, s = d["system"], d["setup"]
    rng = np.random.default_rng(seed)
    controller.reset()
    x = np.array(s.x0, dtype=float)
    xs, us, hr, ht, times, statuses = [x], [], [], [], [], []
    for _ in range(s.T):
        u, info = controller.step(x, np.zeros(3))
        w = rng.uniform(-0.5, 0.5, 3) if disturbed else np.zeros(3)
        x = system.step(x, u, w)
        xs.append(x)
        us.append(u)
        hr.append(info.values.get("h_r", np.nan))
        ht.append(info.values.get("h_tilde", np.nan))
        times.append(info.solve_time)
        statuses.append(info.status)
    X, U = np.array(xs), np.array(us)
    inside = s.X.contains_many(X, tol=1e-6)
    first = int(np.argmax(inside)) if inside.any() else -1
    return {"states": X, "inputs": U, "h_r": np.array(hr), "h_tilde": np.array(ht),
            "fuel": float(np.abs(U).sum()), "entered_X_at": first,
            "stays_in_X_after_entry": bool(first >= 0 and inside[first:].all()),
            "final_in_X": bool(inside[-1]), "final_h_r": float(hr[-1]),
            "median_step_ms": 1e3 * float(np.median(times)),
            "failures": int(sum(st != "ok" for st in statuses))}


def run(out: Path, quick: bool = False, target: str | None = None) -> dict:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    N, T, rhos = (30, 60, (0.0, 0.9)) if quick else (200, 400, (0.0, 0.5, 0.9))
    start = time.perf_counter()
    d = design(N, T)
    ctls = controllers(d, rhos, target)
    system, s, error = d["system"], d["setup"], d["error"]
    rpi = is_rpi(error.E, system.A + system.B @ error.K, s.W, G=system.E, samples=500)
    nominal_runs = ("robust", f"mo_rho{max(rhos):g}")
    results = {"disturbed": {name: closed_loop(c, d, True) for name, c in ctls.items()},
               "nominal": {name: closed_loop(ctls[name], d, False) for name in nominal_runs}}
    metrics = {
        "N": N, "T": T, "rhos": list(rhos), "target": target or "default",
        "units": f"normalized: exact ZOH, T_s = {TS}, mean motion n = {MEAN_MOTION}",
        "rpi": {"lambda": float(error.info["lambda"]), "objective": error.info["objective"],
                "check_ok": rpi.ok, "margin": rpi.margin,
                "semi_axes": np.sqrt(np.linalg.eigvalsh(np.linalg.inv(error.E.P))).tolist()},
        "gamma_f": d["cbf"].gamma_f,
        "runs": {dist: {n: {k: v for k, v in r.items()
                            if k not in ("states", "inputs", "h_r", "h_tilde")}
                        for n, r in res.items()} for dist, res in results.items()},
        "thesis": THESIS, "wall_time_s": time.perf_counter() - start,
    }
    metrics["summary_table"] = _table(results, rhos)
    metrics["plots"] = _plots(results, out)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2, default=float))
    return metrics


def _table(results: dict, rhos: tuple[float, ...]) -> str:
    lines = ["run               | fuel dist. (thesis) | fuel nominal (thesis) | step ms (thesis) "
             "| in X at end",
             "------------------+---------------------+-----------------------+------------------"
             "+------------"]
    th = THESIS
    for name in results["disturbed"]:
        rd, rn = results["disturbed"][name], results["nominal"].get(name)
        key = "robust" if name == "robust" else "multiobjective"
        thesis_row = name == "robust" or name == "mo_rho0.9"
        tf = f"({th['fuel_disturbed'][key]})" if thesis_row else ""
        tn = f"({th['fuel_nominal'][key]})" if thesis_row else ""
        tt = f"({th['step_ms'][key]})" if thesis_row else ""
        fn = f"{rn['fuel']:>12.1f}" if rn else f"{'-':>12}"
        lines.append(f"{name:<17} | {rd['fuel']:>10.1f} {tf:>8} | {fn} {tn:>8} "
                     f"| {rd['median_step_ms']:>8.1f} {tt:>7} | {rd['final_in_X']}/"
                     f"{rn['final_in_X'] if rn else '-'}")
    rob = results["disturbed"]["robust"]["fuel"]
    best = f"mo_rho{max(rhos):g}"
    mo = results["disturbed"][best]["fuel"]
    mon = results["nominal"][best]["fuel"]
    robn = results["nominal"]["robust"]["fuel"]
    lines.append(f"fuel change {best} vs robust: disturbed {100 * (mo - rob) / rob:+.1f}% "
                 f"(thesis -23.9%), nominal {100 * (mon - robn) / robn:+.1f}% (thesis -34%)")
    lines.append("(thesis row: rho unstated; compared with our largest rho)")
    return "\n".join(lines)


def _plots(results: dict, out: Path) -> list[str]:
    paths = []
    for dist in ("disturbed", "nominal"):
        fig, ax = figure(2, 1, (8, 7))
        for name, r in results[dist].items():
            ax[0].semilogy(np.maximum(r["h_r"], 1e-8), label=name)
            ax[1].plot(np.abs(r["inputs"]).sum(axis=1).cumsum(), label=name)
        ax[0].set_ylabel("h_r(x_k)")
        ax[0].set_title(f"rendezvous, {dist} (Fig. 6.1)")
        ax[1].set_ylabel("cumulative fuel Σ‖u‖₁")
        ax[1].set_xlabel("k")
        ax[0].legend(fontsize=7)
        paths.append(save(fig, out / f"fig6_1_h_r_{dist}.png"))
    fig, ax = figure(1, 3, (13, 4))
    for name, r in results["disturbed"].items():
        for j in range(3):
            ax[j].plot(r["states"][:, j], r["states"][:, 3 + j], label=name)
    for j, lab in enumerate("xyz"):
        ax[j].axvline(10, color="k", ls="--")
        ax[j].axvline(-10, color="k", ls="--")
        ax[j].set_xlabel(f"p_{lab}")
        ax[j].set_ylabel(f"v_{lab}")
    ax[0].legend(fontsize=7)
    ax[1].set_title("phase portraits, disturbed (Fig. 6.2)")
    paths.append(save(fig, out / "fig6_2_trajectories.png"))
    return paths
