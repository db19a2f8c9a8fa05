"""Audit A: statuses of every λ of the RPI line search (5.14) on the examples, the chosen one,
and is_rpi of the result (independent of the solve)."""
import warnings

import numpy as np

from balustrade.backends import compile_synthesis
from balustrade.design.rpi import ellipsoidal_rpi
from balustrade.dsl.error_sets import is_rpi
from balustrade.models.unstable2d import unstable2d, unstable2d_setup
from balustrade.problems.rpi import rpi_sdp

warnings.filterwarnings("ignore")
cases = []
system, s = unstable2d(), unstable2d_setup()
cases.append(("unstable2d", system.A, system.B, s.W, s.X, s.U, None))
try:
    from balustrade.models.rendezvous import rendezvous, rendezvous_setup
    r, rs = rendezvous(), rendezvous_setup()
    cases.append(("rendezvous", r.A, r.B, rs.W, rs.X, rs.U, r.E))
except Exception as e:
    print("rendezvous", e)
for name, A, B, W, X, U, G in cases:
    comp = compile_synthesis(rpi_sdp(A, B, W, X, U, G), "sdp")
    sts = []
    for lv in np.linspace(0.05, 0.95, 19):
        sol = comp.solve({"lambda": lv}); sts.append((round(lv, 2), sol.status, None if not sol.ok else round(sol.objective, 6)))
    print(name, sts)
    err = ellipsoidal_rpi(A, B, W, X, U, G)
    chk = is_rpi(err.E, A + B @ err.K, W, G)
    print(name, "chosen", err.info, "is_rpi", chk.ok, chk.margin, chk.method)
