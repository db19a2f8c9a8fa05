"""Audit E: is_rpi on a singular A_cl (no exact check; sampling + support directions only)
accepts an ellipsoid that is not RPI. Independent truth: the trust-region maximum of c_E over
A_cl E + w for each vertex w (geo.max_convex_quadratic_on_ball with L = A_cl E^{1/2}, which
needs no inverse), cross-checked by a dense grid on the sphere."""
import numpy as np

from balustrade.dsl.error_sets import is_rpi
from balustrade.dsl.sets import Box, Ellipsoid
from balustrade.dsl.sets_geometry import max_convex_quadratic_on_ball


def truth(E, A, W):
    L = A @ E._root()
    out = -np.inf
    for w in W.vertices():
        out = max(out, max_convex_quadratic_on_ball(L.T @ E.P @ L, L.T @ E.P @ w, float(w @ E.P @ w)) - 1)
    return out

for n, a, scales in [(3, 0.9, None), (4, 0.8, None), (3, 0.95, [1, 30, 1])]:
    P = np.eye(n) if scales is None else np.diag(np.array(scales, float) ** 2)
    E = Ellipsoid(P, name="E")
    A = np.diag([a] * (n - 1) + [0.0])
    # pick w so that the true margin is +1e-4: bisection on w
    lo, hi = 0.0, 1.0
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        W = Box(-mid * np.ones(n) / np.sqrt(np.diag(P)), mid * np.ones(n) / np.sqrt(np.diag(P)), name="W")
        (lo, hi) = (mid, hi) if truth(E, A, W) < 1e-4 else (lo, mid)
    W = Box(-hi * np.ones(n) / np.sqrt(np.diag(P)), hi * np.ones(n) / np.sqrt(np.diag(P)), name="W")
    t = truth(E, A, W)
    # grid cross-check of the truth on the sphere (n=3 only)
    c = is_rpi(E, A, W)
    print(f"n={n} true margin {t:.3e}  is_rpi ok={c.ok} margin {c.margin:.3e} ({c.method})")

# independent cross-check of "truth" for the last case: the S-lemma dual of e_rpi.py and brute force
import importlib.util

spec = importlib.util.spec_from_file_location("e_rpi_mq", __file__.replace("e_isrpi_singular.py", "e_rpi_mq.py"))
from scipy.optimize import minimize_scalar


def max_quad(P, A, c):
    M = A.T @ P @ A; b = A.T @ P @ c
    Li = np.linalg.inv(np.linalg.cholesky(P)); lam = np.linalg.eigvalsh(Li @ M @ Li.T).max()
    t = lambda tau: c @ P @ c + tau + b @ np.linalg.solve(tau * P - M, b)
    lo = lam * (1 + 1e-12) + 1e-15
    return minimize_scalar(lambda s: t(lo + np.exp(s)), bounds=(-40, 10), method="bounded", options={"xatol": 1e-12}).fun
print("S-lemma dual:", max(max_quad(P, A, w) for w in W.vertices()) - 1)
rng = np.random.default_rng(1); U = rng.standard_normal((400000, n)); U /= np.linalg.norm(U, axis=1)[:, None]
Epts = U @ E._root().T
print("brute force 4e5 boundary points:", max(np.max(np.einsum('ij,jk,ik->i', Epts @ A.T + w, P, Epts @ A.T + w)) for w in W.vertices()) - 1)
