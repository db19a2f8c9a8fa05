"""Audit E: the cost of RowMiss.miss beside the direct Clarabel solves of the rendezvous's
Algorithm 5.2 (N = 200), over a short closed loop; CPU time, medians; and the largest miss."""
import time

import numpy as np

from balustrade.reproduce import rendezvous as R

d = R.design(200, 40)
ctl = R.controllers(d, ())["robust"]
engines = [c.engine for c in (ctl.slack, ctl.filter)]
solve_t, miss_t, misses = [], [], []
for eng in engines:
    run = eng.run
    def timed(q, b, A=None, run=run, eng=eng):
        t = time.process_time(); raw = run(q, b, A) if A is not None else run(q, b)
        solve_t.append(time.process_time() - t)
        t = time.process_time(); m = eng._rows.miss(raw.y, b); miss_t.append(time.process_time() - t)
        if raw.status.success: misses.append(m)
        return raw
    eng.run = timed
x = d["setup"].x0 if hasattr(d["setup"], "x0") else None
out = R.closed_loop(ctl, d, disturbed=True)
print("A sizes", [e._rows._matrix.shape for e in engines], "nnz", [e._rows._matrix.nnz for e in engines])
print(f"solves {len(solve_t)}: median CPU solve (incl. check) {np.median(solve_t)*1e3:.2f} ms, miss {np.median(miss_t)*1e3:.3f} ms; largest miss {max(misses):.1e}")
