"""Reference lowering of (3.28)/(3.30) with no structure exploited (the naive baseline).

Dense Φ = [Φ_x; Φ_u] as the decision variable, the achievability constraint (3.14) and
causality as explicit equality constraints, and the LMI exactly as printed in the thesis
(C^{1/2}Φ and 𝒪 blocks, size 1 + pT + (n+m)(T+1)). It is what a user would write first; the
structured problems of :mod:`balustrade.problems.regret.synthesis` must reach the same optimal
level. Used by the tests (independent check of the levels) and by
``benchmarks/bench_regret.py`` (the naive baseline). ``ops`` is the
:class:`~balustrade.problems.regret.operators.Operators` of the system (read by attribute:
backends do not import problems).
"""

from __future__ import annotations

from typing import Any

import cvxpy as cp
import numpy as np

from balustrade.backends.targets import Target
from balustrade.backends.targets import target as resolve_target


def dense_generalized_regret(ops: Any, x0: np.ndarray | None, omega: float | None,
                             W: np.ndarray, *, zero_x0: bool = False,
                             target: Target | str | None = None) -> tuple[str, float | None]:
    """(status, μ*) of (3.28) (known x₀, ‖w‖² ≤ ω), or of (3.30) with ``zero_x0=True``."""
    n, nd = ops.n, ops.nd
    Nx, Nu = ops.n * (ops.T + 1), ops.m * (ops.T + 1)
    Phi = cp.Variable((Nx + Nu, nd))
    Phi_x, Phi_u = Phi[:Nx], Phi[Nx:]
    cons = [(np.eye(Nx) - ops.Z @ ops.Acal) @ Phi_x - ops.Z @ ops.Bcal @ Phi_u == ops.Ecal]
    for t in range(ops.T + 1):
        after = ops.d_blocks[t].stop
        if after < nd:
            cons.append(Phi_u[ops.u_blocks[t], after:] == 0)
    C = np.block([[ops.Qcal, np.zeros((Nx, Nu))], [np.zeros((Nu, Nx)), ops.Rcal]])
    Ch = np.linalg.cholesky(C).T   # Chᵀ Ch = C
    W1, W2, W3 = ops.partition(W)
    O1, O2, O3 = ops.O_parts
    mu = cp.Variable()
    Cw = Ch @ Phi[:, n:]
    if zero_x0:
        lmi = cp.bmat([[mu * W3 + O3, Cw.T], [Cw, np.eye(Nx + Nu)]])
    else:
        if x0 is None or omega is None:
            raise ValueError("dense (3.28) needs x0 and omega (or zero_x0=True)")
        lam = cp.Variable(nonneg=True)
        top = cp.reshape(mu * (x0 @ W1 @ x0) + x0 @ O1 @ x0 - lam * omega, (1, 1), order="F")
        r12 = cp.reshape(x0 @ O2.T + mu * (x0 @ W2.T), (1, nd - n), order="F")
        c0 = cp.reshape(Ch @ Phi[:, :n] @ x0, (Nx + Nu, 1), order="F")
        lmi = cp.bmat([[top, r12, c0.T],
                       [r12.T, lam * np.eye(nd - n) + O3 + mu * W3, Cw.T],
                       [c0, Cw, np.eye(Nx + Nu)]])
    cons.append(0.5 * (lmi + lmi.T) >> 0)
    prob = cp.Problem(cp.Minimize(mu), cons)
    tgt = resolve_target(target, default="sdp")
    try:
        prob.solve(solver=(tgt.solver or "CLARABEL").upper(), **tgt.solver_options())
    except cp.error.SolverError as exc:
        return f"solver_error: {exc}", None
    return str(prob.status), None if mu.value is None else float(mu.value)
