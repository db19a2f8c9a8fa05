"""The obstacle car of Section 8.3 (SPEC §2.32, §3.7): the compiled PCBF problems (2.24)
and (7.8) with the hard terminal constraint that Algorithm 7.6 samples (the sampler's
``"obstacles"`` problem, :data:`balustrade.learn.sampler.PROBLEMS`)."""

from __future__ import annotations

import numpy as np

from balustrade.learn.sampler import PCBFProblems, compile_pair
from balustrade.models.obstacle_car import TS, obstacle_car, obstacle_setup
from balustrade.problems.obstacles import stopping_extended_problem, stopping_pcbf_problem


def braking_guess(x: np.ndarray, N: int, setup: object = None) -> dict:
    """A primal guess for (2.24) at ``x``: the car (8.1) braking at the largest deceleration
    to ``v = 0`` (then standing) with the steering held, inputs ``(τ, 0)``; it meets
    ``v_N = 0`` whenever ``N`` steps suffice. Started from it, the solver reached
    ``h_PB = 0`` at states where the walk's warm start and a cold start ended ``optimal``
    at ``h_PB`` = 0.021–0.082 (audit D, session 15)."""
    s = obstacle_setup() if setup is None else setup
    f = obstacle_car()
    x = np.asarray(x, dtype=float).reshape(5)
    lo, hi = float(s.U.lb[0]), float(s.U.ub[0])
    z, u = [x], np.zeros((2, int(N)))
    for i in range(int(N)):
        u[0, i] = np.clip(-z[-1][3] / TS, lo, hi)
        z.append(np.asarray(f.step(z[-1], u[:, i]), dtype=float).reshape(5))
    return {"x": np.array(z).T, "u": u}


def obstacle_problems(target: str = "exact", slack_norm: int | str = "inf", N: int | None = None,
                      braking_start: bool = True) -> PCBFProblems:
    """(2.24) (``ξ_N ≡ 0``, hard ``v_N = 0``) and (7.8) for the obstacle car, compiled by
    :func:`~balustrade.learn.sampler.compile_pair`; ``X`` of the result is the sampling
    domain (the arena, headings, speeds 0–4 m/s, steering), not the constraint set.

    ``N`` overrides the horizon 50 (tests use a short one). The problems are nonconvex
    (the disks): a solve reports a local optimum, and infeasible states (no stop outside
    the tightened disks within ``N`` steps, SPEC §2.32) are dropped by the sampler with the
    solver's status recorded as the reason. ``braking_start`` (default): where the walk's
    (2.24) solve leaves ``h_PB > tol`` it is solved again from :func:`braking_guess` and
    the lower value is the label (:attr:`PCBFProblems.slack_guess`; one more solve per
    point outside ``S_PB``)."""
    system, s = obstacle_car(), obstacle_setup()
    n = s.N if N is None else int(N)
    deltas = s.delta_step * np.arange(n)
    args = (system, s.X, s.U, n, deltas, s.delta_step * n)
    slack, slack_cold = compile_pair(stopping_pcbf_problem(*args, slack_norm=slack_norm),
                                     target)
    extended, extended_cold = compile_pair(stopping_extended_problem(*args), target)
    guess = (lambda x: braking_guess(x, n, s)) if braking_start else None
    return PCBFProblems(slack, extended, s.domain, 1.0, slack_cold, extended_cold, guess)


__all__ = ["braking_guess", "obstacle_problems"]
