"""Audit A: is the (5.14) solution RPI on the bicycle linearization (G = G_HEADING)? Own S-lemma
check per vertex of W vs is_rpi's margin, for every λ of the line search."""
import warnings

import cvxpy as cp
import numpy as np

from balustrade.backends import compile_synthesis
from balustrade.dsl import Polytope
from balustrade.dsl.error_sets import is_rpi
from balustrade.examples.bicycle import G_HEADING, V_S, bicycle_sets
from balustrade.models.bicycle import bicycle
from balustrade.problems.rpi import rpi_sdp

warnings.filterwarnings("ignore")
system = bicycle(); X, U, W = bicycle_sets(); x_s = np.array([0.0, 0.0, V_S, 0.0])
A, B = system.jacobians(x_s, np.zeros(2)); A, B = np.asarray(A, float), np.asarray(B, float)
G = np.asarray(G_HEADING, float)
Xs = Polytope(X.H, X.h - X.H @ x_s)
print("A", A.shape, "B", B.shape, "G", G.shape, "W", type(W).__name__, W.dim, "rank A", np.linalg.matrix_rank(A))
comp = compile_synthesis(rpi_sdp(A, B, W, Xs, U, G), "sdp")
n = A.shape[0]
def own_max(P, AK):
    best = -np.inf
    for w in W.vertices():
        gw = G @ w; Mq = AK.T @ P @ AK; b = AK.T @ P @ gw
        t = cp.Variable(); lam = cp.Variable(nonneg=True)
        L = cp.bmat([[cp.reshape(t - gw @ P @ gw - lam, (1, 1)), -b.reshape(1, n)], [-b.reshape(n, 1), lam * P - Mq]])
        pr = cp.Problem(cp.Minimize(t), [(L + L.T) / 2 >> 0]); pr.solve(solver="CLARABEL")
        best = max(best, pr.value)
    return best - 1
for lv in (0.5, 0.8, 0.9, 0.95):
    sol = comp.solve({"lambda": lv})
    if not sol.ok: print(lv, sol.status); continue
    Ev = 0.5 * (sol["E"] + sol["E"].T); P = np.linalg.inv(Ev); P = 0.5 * (P + P.T); K = sol["Y"] @ P
    from balustrade.dsl import Ellipsoid
    chk = is_rpi(Ellipsoid(P), A + B @ K, W, G)
    print(f"λ={lv} {sol.status} obj={sol.objective:.4g} is_rpi margin={chk.margin:.3g} ({chk.worst.get('method')}) own exact margin={own_max(P, A + B @ K):.3g} cond(E)={np.linalg.cond(Ev):.3g}")
