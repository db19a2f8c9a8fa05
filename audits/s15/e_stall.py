"""Audit E: does the stall stop (backends/stall.py) change the answer of the §8.3 PCBF
algorithm on structured-ip? Cold steps (filter reset before each) at random states and
proposals, the same filter built with the stall stop and without (stall_stop=None); compare
status, input, and which solver answered. Short horizon (N=15) for time, seed differs from
session 14's 200 states.  Run: PYTHONPATH=$PWD python .../e_stall.py COUNT SEED"""
import sys
import time

import numpy as np

from balustrade.models.obstacle_car import signed_distance
from balustrade.reproduce import obstacles as O

count = int(sys.argv[1]) if len(sys.argv) > 1 else 40
seed = int(sys.argv[2]) if len(sys.argv) > 2 else 7
N = int(sys.argv[3]) if len(sys.argv) > 3 else 0
rng = np.random.default_rng(seed)
on = O.pcbf_algorithm("structured-ip", horizon=N or None)
off = O.pcbf_algorithm("structured-ip", horizon=N or None, stall_stop=None)
diff = same = 0
t_on = t_off = 0.0
for i in range(count):
    while True:
        p = rng.uniform(-2.5, 2.5, 2)
        if signed_distance(p).min() > 0.02:
            break
    x = np.array([p[0], p[1], rng.uniform(-np.pi, np.pi), rng.uniform(0, 3.5), rng.uniform(-0.3, 0.3)])
    u_p = rng.uniform(-3, 3, 2)
    res = []
    for f in (on, off):
        f.reset(); t = time.process_time()
        u, info = f.step(x, u_p)
        res.append((u, info.status, time.process_time() - t, getattr(info, "fallback", None)))
    t_on += res[0][2]; t_off += res[1][2]
    du = float(np.max(np.abs(res[0][0] - res[1][0])))
    if du > 1e-6 or res[0][1] != res[1][1]:
        diff += 1
        print(f"state {i}: x={np.round(x, 3)} stall: {res[0][1]} u={res[0][0]} ({res[0][2]:.2f}s) | none: {res[1][1]} u={res[1][0]} ({res[1][2]:.2f}s)")
    else:
        same += 1
print(f"same {same} different {diff}; cpu stall {t_on:.1f}s none {t_off:.1f}s")
