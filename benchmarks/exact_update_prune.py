"""``ExactUpdate(prune=False)`` against ``prune=True`` in Algorithm 4.1 (docs/adaptive.md,
"Session 14: ExactUpdate prunes by default")::

    PYTHONPATH=$PWD python -m benchmarks.exact_update_prune [masses] [steps] [seed]

The design of ``reproduce msd-adaptive`` (3 masses, ``fast-convex``, the quick run's 30
steps), one RAPSF per setting of ``prune``, stepped at the same state, taking turns within
each step (which one goes first alternates); the state moves with the first controller's
input (θ* at vertex 1 of Θ₀, uniform disturbances ``|w| <= 1e-3``, seeded). Both estimators
see the same transition: after each step the second controller's last ``(x, u)`` is set to
the first one's, so that the two ``Θ_k`` are the same set in exact arithmetic.

Per step: the time of each step, the rows of each ``Θ_k`` and whether the two are the same
set, decided by LPs (:func:`same_set`: every row of one is valid on the other within
``tol``, both ways). At the end: total and median step times, the largest input difference,
and whether the sets were equal at every step."""

from __future__ import annotations

import sys
import time

import numpy as np

from balustrade.backends.lp import solve_lp
from balustrade.backends.solution import Status
from balustrade.control.rapsf import RAPSF
from balustrade.dsl.sets import Polytope
from balustrade.estimate import ExactUpdate
from balustrade.models.msd import msd_performance
from balustrade.problems.rapsf import model_matrices
from balustrade.reproduce import msd_adaptive as M


def contained(A: Polytope, B: Polytope, tol: float) -> bool:
    """``A ⊆ B``: ``max {H_B[r] θ : θ ∈ A} <= h_B[r] + tol·(1 + |h_B[r]|)`` for every row
    ``r`` of ``B`` (one LP each)."""
    for Hr, hr in zip(B.H, B.h):
        res = solve_lp(Hr, A.H, A.h)
        if res.status is not Status.OPTIMAL or res.value > hr + tol * (1.0 + abs(hr)):
            return False
    return True


def same_set(A: Polytope, B: Polytope, tol: float = 1e-8) -> bool:
    """``A = B`` as sets, by LPs (:func:`contained` both ways)."""
    return contained(A, B, tol) and contained(B, A, tol)


def run(n: int = 3, steps: int = M.STEPS_QUICK, seed: int = 0) -> dict:
    d = M.design(n)
    s, sysm = d["setup"], d["system"]

    def make(prune: bool) -> RAPSF:
        return RAPSF(sysm, d["X0"], M.joint(d), None, s.W, d["K"], s.N, s.Theta0,
                     estimator=ExactUpdate(sysm, s.W, s.Theta0, prune=prune),
                     target=M.TARGET)

    ctrls = {"prune=False": make(False), "prune=True": make(True)}
    names = list(ctrls)
    rng = np.random.default_rng(seed)
    A, B = model_matrices(sysm, s.Theta0.vertices()[1])
    x = np.zeros(2 * n)
    times: dict[str, list[float]] = {t: [] for t in names}
    du, equal, rows = 0.0, [], {t: [] for t in names}
    for k in range(steps):
        up, out = msd_performance(k, x, n), {}
        for t in (names if k % 2 == 0 else names[::-1]):
            t0 = time.perf_counter()
            out[t] = ctrls[t].step(x, up)
            times[t].append(time.perf_counter() - t0)
        first, second = ctrls[names[0]], ctrls[names[1]]
        second._prev = first._prev          # the same transition for both estimators
        du = max(du, float(np.max(np.abs(out[names[0]][0] - out[names[1]][0]))))
        equal.append(same_set(first.Theta, second.Theta))
        for t in names:
            rows[t].append(ctrls[t].Theta.H.shape[0])
        print(k, {t: (round(1e3 * times[t][-1], 1), rows[t][-1], out[t][1].fallback)
                  for t in names}, "same set:", equal[-1], flush=True)
        x = A @ x + B @ out[names[0]][0] + rng.uniform(-1e-3, 1e-3, 2 * n)
    res = {"total_s": {t: float(np.sum(v)) for t, v in times.items()},
           "median_ms": {t: 1e3 * float(np.median(v[1:] or v)) for t, v in times.items()},
           "rows_final": {t: v[-1] for t, v in rows.items()}, "max_du": du,
           "same_set_every_step": all(equal), "steps": steps}
    print(res, flush=True)
    return res


if __name__ == "__main__":
    a = sys.argv[1:]
    run(int(a[0]) if a else 3, int(a[1]) if len(a) > 1 else M.STEPS_QUICK,
        int(a[2]) if len(a) > 2 else 0)
