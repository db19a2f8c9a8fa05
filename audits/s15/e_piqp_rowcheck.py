"""Audit E: row-normalized primal residual max_i (a_i y - b_i)_+ / (max_j|a_ij|) / (1 + |b_i|/max_j|a_ij|)
of PIQP's "optimal" answers (direct backend, fast-convex-qp) on (4.5) of the 3-mass design
(the random instances of e_daqp.py) and on the scaled QPs of e_daqp_scale.py. Tells whether
a feasibility check of PIQP's answers in the rows' own units could be added without
touching well-scaled problems."""
import sys

import numpy as np
import scipy.sparse as sp

from balustrade.backends import compile
from balustrade.backends.daqp_engine import row_norms
from balustrade.backends.solution import Status


def residuals(compiled, params_list):
    eng = compiled.engine
    seen = []
    run = eng.run
    def rec(q, b, A=None):
        raw = run(q, b, A) if A is not None else run(q, b)
        seen.append((b.copy(), None if A is None else A.copy(), raw))
        return raw
    eng.run = rec
    out = []
    for p in params_list:
        seen.clear()
        sol = compiled.solve(p)
        if sol.status != Status.OPTIMAL or not seen:
            continue
        b, A, raw = seen[-1]
        prog = compiled.program
        M = prog.A_matrix(A) if hasattr(prog, "A_matrix") else None
        if M is None:
            pat = sp.csc_matrix(prog.A); pat.sort_indices()
            M = sp.csc_matrix((A if A is not None else pat.data, pat.indices, pat.indptr), shape=pat.shape)
        m0 = sum(k for kind, k in prog.cones if kind == "zero")
        n = row_norms(M)
        r = (M @ raw.y - b) / n
        scale = 1 + np.abs(np.where(np.isfinite(b), b, 0)) / n
        res = np.concatenate([np.abs(r[:m0]) / scale[:m0], np.maximum(np.where(np.isfinite(b[m0:]), r[m0:], 0), 0) / scale[m0:]])
        out.append(float(res.max(initial=0)))
    return np.array(out)

which = sys.argv[1] if len(sys.argv) > 1 else "msd"
if which == "msd":
    src = open(__import__("pathlib").Path(__file__).with_name("e_daqp.py")).read().split("dq = compile")[0]
    sys.argv = ["x", "200", "1"]; g = {}; exec(src, g)
    res = residuals(compile(g["ocp"], "fast-convex-qp"), [p for p, _ in g["insts"]])
else:
    src = open(__import__("pathlib").Path(__file__).with_name("e_daqp_scale.py")).read().split("dq, pq, cl")[0]
    g = {}; exec(src, g)
    rng = np.random.default_rng(0); insts = []
    for k in range(300):
        sc = 10.0 ** rng.choice([-9, -6, -3, 0, 3, 6, 9], size=3)
        if rng.random() < 0.1: sc[rng.integers(3)] = 0.0
        beta = rng.uniform(-1, 1, 3)
        insts.append({"c": rng.uniform(-4, 4, 4), "s": sc, "bb": sc * beta if rng.random() < 0.8 else rng.uniform(-1, 1, 3)})
    res = residuals(compile(g["ocp"], "fast-convex-qp"), insts)
print(which, "optimal answers", res.size, "normalized primal residual quantiles 50/90/99/max:",
      np.quantile(res, [0.5, 0.9, 0.99, 1.0]) if res.size else None, "count > 1e-6:", int((res > 1e-6).sum()))
