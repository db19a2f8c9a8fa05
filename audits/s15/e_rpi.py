"""Audit E: ellipsoidal_rpi's returned (inflated) E checked RPI by an independent S-lemma test
per vertex of W: max_{e'Pe<=1} (Ae+c)'P(Ae+c) <= 1  iff  exists tau>=0 with
[[tau P - A'PA, -A'Pc], [-c'PA, 1 - tau - c'Pc]] PSD (S-lemma, exact for one constraint).
The margin reported is the S-lemma bound on max c_E (bisection on the value t in place of 1).
Run: PYTHONPATH=$PWD python audits/s15/e_rpi.py"""
import numpy as np
from scipy.optimize import minimize_scalar

from balustrade.design.rpi import ellipsoidal_rpi
from balustrade.dsl.sets import Box, Polytope


def max_quad(P, A, c):
    """max over e'Pe<=1 of (Ae+c)'P(Ae+c), by the S-lemma dual: min_{tau>=0} t s.t. the matrix
    [[tau P - A'PA, -A'Pc], [-c'PA, t - tau - c'Pc]] >= 0; for fixed tau the smallest t is
    c'Pc + tau + b'(tau P - A'PA)^+ b (Schur), minimized over tau > lambda_max(A'PA, P)."""
    M = A.T @ P @ A
    b = A.T @ P @ c
    L = np.linalg.cholesky(P)
    Li = np.linalg.inv(L)
    lam = np.linalg.eigvalsh(Li @ M @ Li.T).max()
    def t(tau):
        S = tau * P - M
        return c @ P @ c + tau + b @ np.linalg.solve(S, b)
    lo = lam * (1 + 1e-12) + 1e-15
    r = minimize_scalar(lambda s: t(lo + np.exp(s)), bounds=(-40, 10), method="bounded",
                        options={"xatol": 1e-12})
    return min(r.fun, t(lo + np.exp(10)))

def check(err, A, B, W, G):
    P = err.E.P
    Acl = A + B @ err.K
    G = np.eye(A.shape[0]) if G is None else G
    return max(max_quad(P, Acl, G @ w) for w in W.vertices()) - 1.0

cases = []
rng = np.random.default_rng(0)
for i in range(12):
    n = 2 + i % 3
    A = rng.normal(size=(n, n)); A *= rng.uniform(0.6, 1.3) / max(abs(np.linalg.eigvals(A)))
    B = rng.normal(size=(n, 1))
    w = 10 ** rng.uniform(-3, -1)
    W = Box(-w * np.ones(n), w * np.ones(n), name="W")
    X = Box(-np.ones(n) * 5, np.ones(n) * 5, name="X"); U = Box([-5.0], [5.0], name="U")
    cases.append((f"random{i} n={n}", A, B, W, X, U, None))
for label, (A, B, W, X, U, G) in []:
    try:
        err = ellipsoidal_rpi(A, B, W, X, U, G=G)
    except Exception as e:
        print(f"{label:20s} refused: {type(e).__name__} {str(e)[:100]}")
        continue
    m = check(err, A, B, W, G)
    print(f"{label:20s} inflation {err.info['inflation']:.3e} is_rpi margin {err.info['rpi_margin']:.2e} "
          f"own S-lemma margin {m:.2e} {'OK' if m <= 1e-6 else 'NOT RPI'} ({err.info['rpi_check']})")

# singular closed loops (the exact vertex check is skipped) and the bicycle linearization
extra = []
for i in range(6):
    n = 3
    A = np.diag([rng.uniform(0.5, 1.2), 0.0, 0.0]); A[0, 1] = rng.uniform(0.5, 2); A[1, 2] = rng.uniform(0.5, 2)
    A[2, 2] = 0.0
    B = np.zeros((n, 1)); B[0, 0] = 1.0
    w = 10 ** rng.uniform(-3, -1)
    W = Box(-w * np.ones(n), w * np.ones(n), name="W")
    extra.append((f"singular{i}", A, B, W, Box(-5 * np.ones(n), 5 * np.ones(n), name="X"), Box([-5.0], [5.0], name="U"), None))
from balustrade.examples import bicycle as bic

sysb = bic.bicycle(); X, U, W = bic.bicycle_sets(); xs = np.array([0.0, 0.0, bic.V_S, 0.0])
A, B = sysb.jacobians(xs, np.zeros(2))
extra.append(("bicycle-lin", np.asarray(A), np.asarray(B), W, Polytope(X.H, X.h - X.H @ xs, name="Xs"), U, bic.G_HEADING))
for label, A, B, W, X, U, G in extra:
    try:
        err = ellipsoidal_rpi(A, B, W, X, U, G=G)
    except Exception as e:
        print(f"{label:20s} refused: {type(e).__name__} {str(e)[:150]}")
        continue
    m = check(err, A, B, W, G)
    print(f"{label:20s} inflation {err.info['inflation']:.6e} is_rpi margin {err.info['rpi_margin']:.2e} "
          f"own S-lemma margin {m:.2e} {'OK' if m <= 1e-6 else 'NOT RPI'} ({err.info['rpi_check']}) rank Acl {np.linalg.matrix_rank(A + B @ err.K)}")
