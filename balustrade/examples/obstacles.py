"""The obstacle car of Section 8.3 (SPEC §2.32, §3.7): the compiled PCBF problems (2.24)
and (7.8) with the hard terminal constraint that Algorithm 7.6 samples (the sampler's
``"obstacles"`` problem, :data:`balustrade.learn.sampler.PROBLEMS`)."""

from __future__ import annotations

import numpy as np

from balustrade.learn.sampler import PCBFProblems, compile_pair
from balustrade.models.obstacle_car import obstacle_car, obstacle_setup
from balustrade.problems.obstacles import stopping_extended_problem, stopping_pcbf_problem


def obstacle_problems(target: str = "exact", slack_norm: int | str = "inf", N: int | None = None
                      ) -> PCBFProblems:
    """(2.24) (``ξ_N ≡ 0``, hard ``v_N = 0``) and (7.8) for the obstacle car, compiled by
    :func:`~balustrade.learn.sampler.compile_pair`; ``X`` of the result is the sampling
    domain (the arena, headings, speeds 0–4 m/s, steering), not the constraint set.

    ``N`` overrides the horizon 50 (tests use a short one). The problems are nonconvex
    (the disks): a solve reports a local optimum, and infeasible states (no stop outside
    the tightened disks within ``N`` steps, SPEC §2.32) are dropped by the sampler with the
    solver's status recorded as the reason."""
    system, s = obstacle_car(), obstacle_setup()
    n = s.N if N is None else int(N)
    deltas = s.delta_step * np.arange(n)
    args = (system, s.X, s.U, n, deltas, s.delta_step * n)
    slack, slack_cold = compile_pair(stopping_pcbf_problem(*args, slack_norm=slack_norm),
                                     target)
    extended, extended_cold = compile_pair(stopping_extended_problem(*args), target)
    return PCBFProblems(slack, extended, s.domain, 1.0, slack_cold, extended_cold)


__all__ = ["obstacle_problems"]
