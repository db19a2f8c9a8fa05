"""Cost of a general-polytope ``Θ_k`` in Algorithm 4.1 (audit session 13, finding 7:
``ExactUpdate(prune=False)`` took 37 s for 40 steps, mostly vertex enumeration of the growing
polytope): each accepted new ``Θ_k`` is enumerated once, for both the nesting check of
Assumption 4.2 and ``s_jr`` (it was enumerated twice)."""

from __future__ import annotations

import numpy as np

from balustrade.control.rapsf import RAPSF
from balustrade.dsl.sets import Polytope
from balustrade.estimate import ExactUpdate

N = 4


class _Counted(Polytope):
    """A polytope that counts its vertex enumerations."""

    calls = 0

    def vertices(self) -> np.ndarray:
        type(self).calls += 1
        return super().vertices()


class _CountingExact(ExactUpdate):
    def update(self, x_prev, u_prev, x_next, **kw):
        new = super().update(x_prev, u_prev, x_next, **kw)
        return None if new is None else _Counted(new.H, new.h, name=new.name)


def test_new_theta_is_enumerated_once_per_step(rapsf_toy) -> None:
    t = rapsf_toy
    est = _CountingExact(t.sys, t.W, t.Theta0)
    ctrl = RAPSF(t.sys, t.X0, t.F, t.G, t.W, t.K, N, t.Theta0, estimator=est,
                 target="fast-convex")
    rng = np.random.default_rng(3)
    theta = np.array([0.9, 0.2])
    x, accepted = np.array([0.5, 0.1]), 0
    for k in range(6):
        before = (_Counted.calls, ctrl.Theta)
        u, info = ctrl.step(x, np.array([np.sin(k)]))
        if ctrl.Theta is not before[1]:
            accepted += 1
            assert _Counted.calls - before[0] == 1, (k, _Counted.calls - before[0])
        x = t.sys.step(x, u, theta, rng.uniform(-0.004, 0.004, 2))
    assert accepted >= 3
