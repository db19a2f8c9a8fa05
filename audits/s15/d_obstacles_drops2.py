"""Audit D: the sampler on states inside a disc at low speed (where (2.24) with v_N = 0 must be
infeasible: the car cannot leave the disc within N T_s = 1 s) and just outside."""
import numpy as np

from balustrade.examples.obstacles import obstacle_problems
from balustrade.learn.sampler import Evaluator, Seed

ev = Evaluator(obstacle_problems())
# reachable distance from v = 0 within 1 s with tau in [-5, 2] and v_N = 0: accelerate t1 at 2,
# brake at 5: t1 + 2 t1/5 <= 1 -> t1 = 0.714, distance = 0.5*2*t1^2 + (2 t1)^2/(2*5) = 0.714 m
for x in ([0, 0, 0, 0, 0], [0.0, 0.0, 1.0, 0.0, 0.3], [0.8, 0.8, 0, 0.0, 0.0], [0.0, 0.0, 0, 4.0, 0.0],
          [0.0, 0.0, 0, 0.05, 0.0]):
    s, _ = ev.point(np.array(x, float), Seed(np.array(x, float)))
    print(x, "ok", s.ok, "h", s.h, "h_pb", s.h_pb, "in_s", s.in_s, "reason", repr(s.reason))
