"""Measurement (issue #14/#16, session 12): CasADi's trust-region SQP ``feasiblesqpmethod``
on the lane change's slow first steps, against the ``robust-sqp`` attempts and IPOPT.

The NLPs are those the controllers solve (``reproduce/lane_change.py`` ``controllers()``,
configuration ``converging``, seed 0): the (5.15) of Algorithm 5.2 at steps 0–9 and the (6.15)
of Algorithm 6.4 at steps 0–1, recorded along the Python closed loops (each compiled problem's
own ``nlp``, bounds and parameter vector, so every solver sees the same NLP, scaling included).
Per NLP and start: status, objective (relative to IPOPT's), iterations, wall time (under
load; the solvers are run interleaved, ``--reps`` times, median time).

feasiblesqpmethod needs a start that satisfies every bound and row to ``feas_tol``
(else ``No_Feasible_Initialization`` at once), so it runs from (a) the cold start the chain's
retries use, (b) the controller's own warm start, (c) the candidate (5.17) (5.2, k ≥ 1).

Run: ``PYTHONPATH=$PWD python benchmarks/lane_fsqp.py [--steps 10] [--reps 3]``.
Throwaway measurement script, not part of ``balustrade bench``.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time

import casadi as ca
import numpy as np

from balustrade.backends.casadi_backend import QPSOL_DEFAULTS, solver_options
from balustrade.control.fallbacks import project
from balustrade.control.robust_steps import minimal_slacks
from balustrade.reproduce import lane_change as lc

FSQP = "feasiblesqpmethod"
QUIET = {"print_header": False, "print_iteration": False, "print_status": False}


@contextlib.contextmanager
def _mute():
    """feasiblesqpmethod prints ("print solve type…", "Rejected inner iterates") to stdout."""
    sys.stdout.flush()
    fd, saved = sys.stdout.fileno(), os.dup(sys.stdout.fileno())
    with open(os.devnull, "w") as null:
        os.dup2(null.fileno(), fd)
        try:
            yield
        finally:
            sys.stdout.flush()
            os.dup2(saved, fd)
            os.close(saved)


def record(d: lc.BicycleDesign, steps: int, seed: int) -> list[dict]:
    """The (5.15) of 5.2 at steps 0…steps-1 and the (6.15) of 6.4 at steps 0–1."""
    ctrls = lc.controllers(d)
    ws = lc.disturbances(d, seed, max(steps, 2))
    out: list[dict] = []
    rob, mo = ctrls["robust"], ctrls["multiobjective"]

    def tap(problem: object, label: str, ctrl: object) -> None:
        solve = problem.solve

        def recorded(params: dict, warm_start: object = None, **kw: object) -> object:
            sol = solve(params, warm_start=warm_start, **kw)
            cand = getattr(ctrl, "candidate", None)
            out.append({"label": label, "c": problem, "params": dict(params), "ctrl": ctrl,
                        "warm": warm_start, "candidate": None if cand is None else
                        cand.as_dict(), "chain": sol})
            return sol
        problem.solve = recorded

    for ctrl, prob, label, n in ((rob, rob.slack, "5.15", steps), (mo, mo.problem, "6.15", 2)):
        tap(prob, label, ctrl)
        ctrl.reset()
        x = lc.X0.copy()
        for k in range(n):
            u, _ = ctrl.step(x, lc.human(x))
            x = d.system.step(x, u, ws[k])
        del prob.solve
    for k, r in enumerate(x for x in out if x["label"] == "5.15"):
        r["k"] = k
    for k, r in enumerate(x for x in out if x["label"] == "6.15"):
        r["k"] = k
    return out


#: added to the minimal slacks of a start so that its slack rows hold strictly
MARGIN = 1e-6


def feasible_start(ctrl: object, x0: np.ndarray, z: np.ndarray | None = None,
                   v: np.ndarray | None = None, xi_N_margin: float = 0.0) -> dict:
    """A start of (5.15) feasible by construction: ``(z, v)`` given (the candidate (5.17))
    or rolled out from ``z_0 = x_0`` with ``v_i = π_f(z_i)`` projected onto ``U ⊖ κ(E)``
    (nominal model, ``w = 0``); the slacks :func:`minimal_slacks`, ``ξ`` plus :data:`MARGIN`."""
    if z is None:
        N = ctrl.deltas.size
        zs, vs = [np.asarray(x0, dtype=float)], []
        for _ in range(N):
            u = project(np.asarray(ctrl.pi_f(zs[-1]), dtype=float).reshape(-1), ctrl.U_E)
            vs.append(u)
            zs.append(ctrl.system.step(zs[-1], u, np.zeros(ctrl.system.nw)))
        z, v = np.array(zs).T, np.array(vs).T
    xi, xi_N = minimal_slacks(ctrl.X_E, ctrl.h_f, ctrl.deltas, z)
    # no margin on ξ_N by default: weighted by α_f = 1e6, 1e-6 adds 1 to h̃ (the terminal
    # row holds without); with it the first QP is no longer degenerate (docs/vehicles.md)
    return {"z": z, "v": v, "xi": xi + MARGIN, "xi_N": np.array([[xi_N + xi_N_margin]])}


def start_of(c: object, p: np.ndarray, warm: object) -> np.ndarray:
    return np.asarray(c._initial_guess(warm, p)[0], dtype=float).reshape(-1)


def violation(c: object, w: np.ndarray, p: np.ndarray) -> float:
    g = c._g(w, p)
    return float(max(np.max(g - c.ubg, initial=0), np.max(c.lbg - g, initial=0),
                     np.max(w - c.ubx, initial=0), np.max(c.lbx - w, initial=0)))


def run(solver: ca.Function, c: object, p: np.ndarray, x0: np.ndarray) -> dict:
    t0 = time.perf_counter()
    with _mute():
        res = solver(x0=x0, p=p, lbx=c.lbx, ubx=c.ubx, lbg=c.lbg, ubg=c.ubg)
    t = time.perf_counter() - t0
    st = solver.stats()
    w = np.asarray(res["x"]).reshape(-1)
    return {"status": st.get("return_status"), "success": bool(st.get("success")),
            "f": float(res["f"]), "iter": int(st.get("iter_count", -1)), "time": t,
            "viol": violation(c, w, p) if np.all(np.isfinite(w)) else np.inf}


def solvers(c: object, max_iter: int) -> dict[str, ca.Function]:
    """IPOPT (reference), the chain's first sqpmethod attempt, feasiblesqpmethod (qpoases,
    its default QP solver, and qrqp with the backend's qrqp options)."""
    nlp = c.nlp
    qrqp = {"qpsol": "qrqp", "qpsol_options": QPSOL_DEFAULTS["qrqp"]}
    qpoases = {"qpsol_options": {"printLevel": "none", "error_on_fail": False}}
    common = {**QUIET, "max_iter": max_iter}
    return {
        "ipopt": ca.nlpsol("ref", "ipopt", nlp, solver_options("ipopt")),
        "sqp": c.solver,
        "fsqp-qpoases": ca.nlpsol("f1", FSQP, nlp, {**common, **qpoases}),
        "fsqp-qrqp": ca.nlpsol("f2", FSQP, nlp, {**common, **qrqp}),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--reps", type=int, default=3,
                    help="repetitions of the IPOPT and sqpmethod solves (median time)")
    ap.add_argument("--max-iter", type=int, default=100,
                    help="feasiblesqpmethod's iteration limit (robust-sqp: 500; one run each: "
                         "with qrqp 500 iterations take 1-2 minutes under load)")
    ap.add_argument("--xi-n-margin", type=float, default=0.0,
                    help="added to the terminal slack of the feasible starts (e.g. 1e-6)")
    args = ap.parse_args()
    d = lc.design(lc.config("converging"))
    recs = record(d, args.steps, args.seed)
    built: dict[int, dict] = {}
    print("problem k start        solver        status                               "
          "objective  rel.obj    iter  time[ms]  viol")
    for r in recs:
        c, p = r["c"], r["c"].ocp.pack_parameters(r["params"])
        sv = built.setdefault(id(c), solvers(c, args.max_iter))
        starts = {"cold": start_of(c, p, None)}
        if r["warm"] is not None:
            starts["warm"] = start_of(c, p, r["warm"])
        if r["candidate"] is not None and r["k"] > 0:
            starts["candidate"] = start_of(c, p, r["candidate"])
            if r["label"] == "5.15":
                cd = r["candidate"]
                starts["cand+slk"] = start_of(c, p, feasible_start(
                    r["ctrl"], r["params"]["x0"], cd["z"], cd["v"], args.xi_n_margin))
        if r["label"] == "5.15":
            starts["rollout"] = start_of(c, p, feasible_start(r["ctrl"], r["params"]["x0"],
                                                               xi_N_margin=args.xi_n_margin))
        cold, ch = starts["cold"], r["chain"]
        print(f"{r['label']:7} {r['k']} chain (closed loop): {ch.status.value}, "
              f"{ch.iterations} it., {1e3 * ch.solve_time:.1f} ms, by {ch.solver}: "
              f"{ch.message[:150]}", flush=True)
        ref = [run(sv["ipopt"], c, p, cold) for _ in range(args.reps)]
        f_ref = ref[0]["f"]
        rows = [("cold", "ipopt", ref), ("cold", "sqp", None)]
        rows += [(s, name, None) for s in starts for name in ("fsqp-qpoases", "fsqp-qrqp")]
        for start, name, res in rows:
            if res is None:
                reps = args.reps if name == "sqp" else 1
                res = [run(sv[name], c, p, starts[start]) for _ in range(reps)]
            a = res[0]
            # relative to IPOPT's objective (the declared one: the NLP's is scaled by
            # c.objective_scale, so an absolute test would be 1e4 times too loose here)
            rel = abs(a["f"] - f_ref) / max(abs(f_ref), 1e-12 * c.objective_scale) \
                if np.isfinite(a["f"]) else np.inf
            ok = a["success"] and rel <= 1e-6 and a["viol"] <= 1e-6
            print(f"{r['label']:7} {r['k']} {start:10} {name:13} {str(a['status'])[:36]:36} "
                  f"{a['f'] / c.objective_scale:10.6g} {rel:9.1e} {a['iter']:5d} "
                  f"{1e3 * np.median([x['time'] for x in res]):8.1f}"
                  f"  {a['viol']:.1e} {'OK' if ok else '--'}"
                  f"  (start viol {violation(c, starts[start], p):.1e})", flush=True)


if __name__ == "__main__":
    main()
