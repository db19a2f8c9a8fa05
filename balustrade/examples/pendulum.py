"""The damped pendulum example of Section 7.5 (SPEC §3.5): its terminal CBF (7.11) and the
compiled PCBF problems (2.24) and (7.8) that Algorithm 7.6 samples (the sampler's
``"pendulum"`` problem, :data:`balustrade.learn.sampler.PROBLEMS`)."""

from __future__ import annotations

from balustrade.design.terminal_cbf import synthesize_terminal_cbf
from balustrade.learn.sampler import PCBFProblems, compile_pair
from balustrade.models.pendulum import pendulum, pendulum_setup
from balustrade.problems.pcbf import extended_pcbf_problem, pcbf_slack_problem
from balustrade.problems.terminal_cbf import TerminalCBF


def pendulum_terminal_cbf() -> TerminalCBF:
    """The terminal CBF (7.11) of the pendulum, state rows tightened by ``Δ_{N−1}``."""
    system, s = pendulum(), pendulum_setup()
    return synthesize_terminal_cbf(system.A, system.B, s.X, s.U, delta_N=s.deltas[-1])


def pendulum_problems(target: str = "fast-sqp", slack_norm: int = 1) -> PCBFProblems:
    """(2.24) and (7.8) for the pendulum of Section 7.5 (SPEC §3.5), compiled by
    :func:`~balustrade.learn.sampler.compile_pair`.

    The fast SQP warm-started along lines/snake grids needs ≈ 1 SQP iteration per solve
    and is 2.5–15× faster than the warm-started interior point (``target="exact"``); with
    the backend's eigenvalue-clipping convexification it agrees with the cvxpy target to
    ≈ 3e-8 relative on the Section 7.5 range (tested to 1e-6). Cold starts use the
    ``sampling-cold`` target (the SQP from the default initial guess is slower and less
    reliable on these LP-like problems)."""
    system, s = pendulum(), pendulum_setup()
    h_f = pendulum_terminal_cbf()
    args = (system, s.X, s.U, h_f, s.N, s.deltas)
    slack, slack_cold = compile_pair(
        pcbf_slack_problem(*args, alpha_f=s.alpha_f, slack_norm=slack_norm), target)
    extended, extended_cold = compile_pair(extended_pcbf_problem(*args), target)
    return PCBFProblems(slack, extended, s.X, 1.0, slack_cold, extended_cold)


__all__ = ["pendulum_problems", "pendulum_terminal_cbf"]
