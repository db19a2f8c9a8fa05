"""Audit E: cost of PiqpEngine's row check (_row_miss per solve; _row_norms when A(p) changes)
beside the PIQP solve, on (4.5) of the 3-mass design (and 8 masses with argv[1] == "8"),
median over the solves of e_daqp.py's instances; CPU time (process_time) and wall."""
import sys
import time

import numpy as np

from balustrade.backends import compile

n_mass = int(sys.argv[1]) if len(sys.argv) > 1 else 3
from balustrade.reproduce import msd_adaptive

d = msd_adaptive.design(n_mass)
ctrl = msd_adaptive.adaptive_controller(d, target="fast-convex-qp")
nv = len(ctrl.vertices)
ocp = ctrl._problem(ctrl.N, n_vertices=nv)
c = compile(ocp, "fast-convex-qp")
eng = c.engine
print("A", c.program.A.shape, "nnz", c.program.A.nnz)
rng = np.random.default_rng(0)
V = d["X0"].vertices() if n_mass == 3 else None
solve_t, miss_t, norm_t = [], [], []
for k in range(30):
    x = (V[rng.integers(len(V))] * rng.uniform(0.3, 0.9)) if V is not None else rng.uniform(-0.05, 0.05, 2 * n_mass)
    p = {"x0": x, "u_p": rng.uniform(-3, 3, n_mass), "theta": ctrl.vertices.T, "s": ctrl._s}
    pk = ocp.pack_parameters(p); prog = c.program
    q, b, A = prog.q(pk), prog.b(pk), prog.A_data(pk)
    t = time.process_time(); raw = eng.run(q, b, A); solve_t.append(time.process_time() - t)
    t = time.process_time()
    for _ in range(20): eng._row_miss(raw.y, b)
    miss_t.append((time.process_time() - t) / 20)
    t = time.process_time()
    for _ in range(5): eng._row_norms()
    norm_t.append((time.process_time() - t) / 5)
print(f"{n_mass} masses: median CPU per solve (incl. check) {np.median(solve_t)*1e3:.3f} ms, _row_miss {np.median(miss_t)*1e3:.3f} ms, _row_norms {np.median(norm_t)*1e3:.3f} ms; last status {raw.status}")
