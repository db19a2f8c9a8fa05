"""Audit E: can kkt_residual (backends/daqp_engine.py) pass a wrong point?"""
import numpy as np
import scipy.sparse as sp

from balustrade.backends.daqp_engine import kkt_residual


def case(name, P, q, A, b, m0, y, z):
    r = kkt_residual(sp.csc_matrix(P), np.array(q, float), sp.csc_matrix(A), np.array(b, float), m0,
                     np.array(y, float), np.array(z, float))
    print(f"{name:60s} residual {r:.2e}  accepted={r <= 1e-8}")

# min y^2 - ... : 1) tiny row: 1e-9*y <= 0, min (y-1)^2 -> y*=0; claim y=1 (z=0)
case("tiny row 1e-9 y<=0, min (y-1)^2, claim y=0.01,z=0 (opt y=0)", [[2.]], [-2.], [[1e-9]], [0.], 0, [0.01], [0.0])
# 2) infinite b with positive multiplier: min -y, y <= inf (unbounded); claim y=0, z=1
case("unbounded min -y, row y<=inf, claim y=0 z=1", [[0.]], [-1.], [[1.]], [np.inf], 0, [0.], [1.])
# 3) NaN b treated as no row
case("row y<=NaN, min (y-1)^2, claim y=1", [[2.]], [-2.], [[1.]], [np.nan], 0, [1.], [0.])
# 4) -inf b (infeasible row) treated as no row
case("row y<=-inf (infeasible), min (y-1)^2, claim y=1", [[2.]], [-2.], [[1.]], [-np.inf], 0, [1.], [0.])
# 5) huge stationarity cancellation: z huge on a row
case("min (y-1)^2, y<=0 with row 1e9*y <= 0; claim y=1e-9? ", [[2.]], [-2.], [[1e9]], [0.], 0, [1e-17], [2e-9])
# 6) sign of z: scaled by max|ATz|
case("dual sign: z=-1e-3 on inactive row with huge ATz on other", [[0,0],[0,0]], [1., -1e7], [[-1., 0],[0, 1.],[0,-1]], [0., 1., 0], 0, [0., 1.], [1., 1e7, 0])
