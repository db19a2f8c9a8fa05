"""Hot-started active-set QP (qpOASES through CasADi's ``conic``) against the direct backend's
PIQP on the QP (4.5) of Algorithm 4.1 (thesis Chapter 4, SPEC §2.21), on the same matrices
(docs/adaptive.md, "Hot-started active set (session 12)")::

    PYTHONPATH=$PWD python -m benchmarks.rapsf_hotqp [masses] [steps] [order] [cpu_s]

The closed loop of :mod:`benchmarks.rapsf_split` (the design of ``reproduce msd-adaptive``,
box update, ``fast-convex``) runs as usual; at every solve of (4.5) the direct backend's
lowered data (``q``, ``b`` and the values of ``A(p)`` on its fixed pattern,
:class:`~balustrade.backends.passes.to_conic.ConicProgram`) are also handed to one
``ca.conic(..., "qpoases", ...)`` Function whose memory lives across the loop: CasADi's
interface calls qpOASES' ``init`` on the first call and ``SQProblem::hotstart(H, g, A, …)``
on every later one (the ``called_once`` flag of ``qpoases_interface.cpp``), i.e. from the
previous working set, with the new ``H`` and ``A`` set up again every call (there is no
vector-only hot start through this interface, even when ``A`` is unchanged). The two
solvers take turns in going first (``order``: ``alternate``, the default).

A qpOASES answer counts as optimal only if its flag is ``SUCCESSFUL_RETURN`` *and* the KKT
conditions of the lowered QP hold at its point and multipliers (:func:`kkt_residual`);
``RET_MAX_NWSR_REACHED`` is a limit stop, the infeasibility flags are an unconfirmed
"infeasible", anything else a failure (:func:`status_of`). The loop itself always applies
PIQP's answer (this is a measurement, not a controller).
"""

from __future__ import annotations

import sys
import time

import casadi as ca
import numpy as np
import scipy.sparse as sp

from balustrade.reproduce import msd_adaptive
from benchmarks.bench_rapsf import Loop

#: qpOASES options: (4.5)'s Hessian is only positive semidefinite (the cost weighs
#: ``v_0 − u_p`` only: 3 of 107 diagonal entries for 3 masses), hence ``semidef``; no
#: regularisation (``enableRegularisation`` adds ``εI`` and removes it by proximal steps:
#: measured 4.4e-9 on the inputs and 9e-9 on the objective against PIQP, twice the
#: working-set changes, against 6.9e-10 / 3.8e-10 without, 40 steps of 3 masses)
QPOASES_OPTIONS = {"printLevel": "none", "hessian_type": "semidef", "error_on_fail": False}

#: qpOASES return flags (``qpOASES::returnValue``) named here
SUCCESSFUL_RETURN = 0
RET_MAX_NWSR_REACHED = 64
#: KKT tolerance (relative to the data's scale) for a qpOASES "success" to count as optimal
KKT_TOL = 1e-8


def _sparsity(M: sp.spmatrix) -> ca.Sparsity:
    M = sp.csc_matrix(M)
    M.sort_indices()
    return ca.Sparsity(M.shape[0], M.shape[1], M.indptr.tolist(), M.indices.tolist())


def status_of(flag: int, infeasible: bool, kkt: float) -> str:
    """The honest status of one qpOASES call: ``optimal`` only for ``SUCCESSFUL_RETURN``
    with KKT residual <= :data:`KKT_TOL`."""
    if flag == SUCCESSFUL_RETURN:
        return "optimal" if kkt <= KKT_TOL else "failed (success flag, KKT not met)"
    if flag == RET_MAX_NWSR_REACHED:
        return "max_iterations"
    return "infeasible (unconfirmed)" if infeasible else "failed"


class HotQpoases:
    """One qpOASES ``conic`` for a lowered QP ``min ½yᵀPy + qᵀy, A y + s = b, s ∈ {0}×R₊``,
    evaluated through a ``FunctionBuffer`` (one memory: hot from the second call)."""

    def __init__(self, prog, options: dict | None = None, plugin: str = "qpoases"):
        if prog.conic:
            raise ValueError("HotQpoases: LP/QP only")
        P = sp.csc_matrix(prog.P)
        self.P = (P + P.T - sp.diags(P.diagonal())).tocsc()     # prog.P is the upper part
        self.P.sort_indices()
        self.A = sp.csc_matrix(prog.A)
        self.A.sort_indices()
        self.m0 = sum(m for kind, m in prog.cones if kind == "zero")
        opts = dict(QPOASES_OPTIONS if plugin == "qpoases" else {}, **(options or {}))
        self.fn = ca.conic("hot", plugin, {"h": _sparsity(self.P), "a": _sparsity(self.A)},
                           opts)
        self.buffer, self._eval = self.fn.buffer()
        self.args = {n: np.zeros(self.fn.nnz_in(n)) for n in self.fn.name_in()}
        self.res = {n: np.zeros(self.fn.nnz_out(n)) for n in self.fn.name_out()}
        for i, n in enumerate(self.fn.name_in()):
            self.buffer.set_arg(i, memoryview(self.args[n]))
        for i, n in enumerate(self.fn.name_out()):
            self.buffer.set_res(i, memoryview(self.res[n]))
        self.args["h"][:] = self.P.data
        self.args["a"][:] = self.A.data
        self.args["lbx"][:], self.args["ubx"][:] = -np.inf, np.inf
        self.args["lba"][:] = -np.inf

    def run(self, q: np.ndarray, b: np.ndarray, A: np.ndarray | None) -> dict:
        self.args["g"][:] = q
        self.args["uba"][:] = b
        self.args["lba"][:self.m0] = b[:self.m0]
        if A is not None:
            self.args["a"][:] = A
        c0, t0 = time.process_time(), time.perf_counter()
        self._eval()
        elapsed, cpu = time.perf_counter() - t0, time.process_time() - c0
        st = self.buffer.stats()
        y, z = self.res["x"].copy(), self.res["lam_a"].copy()
        values = self.A.data if A is None else A
        kkt = kkt_residual(self.P, q, sp.csc_matrix((values, self.A.indices, self.A.indptr),
                                                    shape=self.A.shape), b, self.m0, y, z)
        # the stats carry qpOASES' message, ``success`` (flag == SUCCESSFUL_RETURN) and
        # CasADi's unified status (LIMITED: RET_MAX_NWSR_REACHED; INFEASIBLE: the
        # infeasibility flags), not the numeric flag itself
        unified = str(st.get("unified_return_status"))
        flag = SUCCESSFUL_RETURN if st.get("success") else \
            RET_MAX_NWSR_REACHED if unified.endswith("LIMITED") else -1
        return {"time": elapsed, "cpu": cpu, "y": y, "iterations": int(st.get("iter_count", -1)),
                "words": str(st.get("return_status")), "kkt": kkt,
                "status": status_of(flag, unified.endswith("INFEASIBLE"), kkt)}


def kkt_residual(P, q, A, b, m0: int, y: np.ndarray, z: np.ndarray) -> float:
    """Largest scaled KKT violation of ``min ½yᵀPy + qᵀy, A_eq y = b_eq, A_in y <= b_in`` at
    ``(y, z)`` (``z`` CasADi's ``lam_a``: ``P y + q + Aᵀz = 0``, ``z >= 0`` on the
    inequality rows): stationarity, primal feasibility, dual sign, complementarity."""
    r = A @ y - b
    scale = 1.0 + max(np.max(np.abs(b)), np.max(np.abs(q)))
    stat = np.max(np.abs(P @ y + q + A.T @ z))
    prim = max(np.max(np.abs(r[:m0]), initial=0.0), np.max(r[m0:], initial=0.0))
    dual = max(0.0, -np.min(z[m0:], initial=0.0))
    comp = np.max(np.abs(z[m0:] * r[m0:]), initial=0.0)
    return float(max(stat, prim, dual, comp) / scale)


def compare(masses: int, steps: int, order: str = "alternate", options: dict | None = None,
            plugin: str = "qpoases") -> dict:
    """The closed loop on ``fast-convex`` with every (4.5) solve also given to the hot
    ``conic``; per solve: times, iterations, statuses, ``|v_0|`` and objective differences.
    Step 0 compiles (4.5) inside the step, so the rows are the solves of steps ``1 …
    steps − 1`` (the first of them qpOASES' cold ``init``)."""
    d = msd_adaptive.design(masses)
    ctrl = msd_adaptive.adaptive_controller(d, target="fast-convex")
    loop = Loop(d, ctrl.step, steps)
    rows: list[dict] = []
    hot: dict[int, HotQpoases] = {}
    wrapped: set[int] = set()

    def wrap(compiled) -> None:
        engine, prog = compiled.engine, compiled.program
        run = engine.run
        hot[id(compiled)] = HotQpoases(prog, options, plugin)
        last_A: list[np.ndarray | None] = [None]

        def both(q, b, A=None):
            qp = hot[id(compiled)]
            first = order == "qpoases" or (order == "alternate" and len(rows) % 2 == 1)
            if first:
                other = qp.run(q, b, A)
            c0, t0 = time.process_time(), time.perf_counter()
            raw = run(q, b) if A is None else run(q, b, A)
            t_piqp, c_piqp = time.perf_counter() - t0, time.process_time() - c0
            if not first:
                other = qp.run(q, b, A)
            v = [np.asarray(compiled.ocp.unpack_variables(y[:prog.n_w].copy())["v"])[:, 0]
                 for y in (raw.y, other["y"])]
            cost = [0.5 * y @ qp.P @ y + q @ y for y in (raw.y, other["y"])]
            changed = A is not None and (last_A[0] is None or not np.array_equal(A, last_A[0]))
            last_A[0] = None if A is None else A.copy()
            rows.append({"piqp_time": t_piqp, "piqp_cpu": c_piqp, "qp_cpu": other["cpu"],
                         "piqp_iter": raw.iterations,
                         "piqp_status": raw.status.value, "qp_time": other["time"],
                         "qp_iter": other["iterations"], "qp_status": other["status"],
                         "qp_words": other["words"], "kkt": other["kkt"],
                         "dv0": float(np.max(np.abs(v[0] - v[1]))),
                         "dobj": float(abs(cost[0] - cost[1])), "A_changed": changed})
            return raw

        engine.run = both

    for k in range(steps):
        for compiled in ctrl._compiled.values():
            if id(compiled) not in wrapped:
                wrapped.add(id(compiled))
                wrap(compiled)
        loop(k)
    return {"masses": masses, "steps": steps, "rows": rows, "fallbacks": loop.fallbacks,
            "plugin": plugin}


def summary(r: dict, skip: int = 1) -> str:
    """Medians/worst over the solves after the first ``skip`` (the cold ``init``)."""
    rows = r["rows"][skip:]
    if not rows:
        return "no solves"
    col = {k: np.array([x[k] for x in rows]) for k in (
        "piqp_time", "qp_time", "piqp_cpu", "qp_cpu", "piqp_iter", "qp_iter", "dv0", "dobj",
        "kkt")}
    zero = col["qp_time"][col["qp_iter"] == 0]
    zero_cpu = col["qp_cpu"][col["qp_iter"] == 0]
    first, name = r["rows"][0], r.get("plugin", "qpoases")
    statuses: dict[str, int] = {}
    for x in rows:
        key = f"PIQP {x['piqp_status']} / {name} {x['qp_status']}"
        statuses[key] = statuses.get(key, 0) + 1
    lines = [
        f"{r['masses']} masses, {len(rows)} hot solves after 1 cold (cold: {name} "
        f"{1e3 * first['qp_time']:.1f} ms, {first['qp_iter']} working-set changes, "
        f"{first['qp_status']}; PIQP {1e3 * first['piqp_time']:.1f} ms); "
        f"{sum(x['A_changed'] for x in rows)} solves with a changed A",
        f"  PIQP    solve median {1e3 * np.median(col['piqp_time']):8.3f} ms, worst "
        f"{1e3 * col['piqp_time'].max():8.3f} ms (CPU median "
        f"{1e3 * np.median(col['piqp_cpu']):.3f} ms); iterations median "
        f"{np.median(col['piqp_iter']):.0f}, max {col['piqp_iter'].max()}",
        f"  {name:<7} solve median {1e3 * np.median(col['qp_time']):8.3f} ms, worst "
        f"{1e3 * col['qp_time'].max():8.3f} ms (CPU median "
        f"{1e3 * np.median(col['qp_cpu']):.3f} ms); working-set changes median "
        f"{np.median(col['qp_iter']):.0f}, max {col['qp_iter'].max()}; with 0 changes "
        f"({zero.size} solves) median "
        f"{1e3 * np.median(zero) if zero.size else float('nan'):.3f} ms (CPU "
        f"{1e3 * np.median(zero_cpu) if zero.size else float('nan'):.3f} ms)",
        f"  max |v_0 difference| {col['dv0'].max():.2e}, max |objective difference| "
        f"{col['dobj'].max():.2e}, max KKT residual of {name} {col['kkt'].max():.2e}",
        "  statuses: " + "; ".join(f"{k}: {v}" for k, v in statuses.items()),
    ]
    return "\n".join(lines)


def main(argv: list[str]) -> None:
    masses = int(argv[0]) if argv else 3
    steps = int(argv[1]) if len(argv) > 1 else 150
    order = argv[2] if len(argv) > 2 else "alternate"
    # 8 masses: qpOASES is dense (A: 28980 x 587 doubles, 136 MB); each call is capped
    options = {"CPUtime": float(argv[3])} if len(argv) > 3 else None
    print(summary(compare(masses, steps, order, options)))


if __name__ == "__main__":
    main(sys.argv[1:])
