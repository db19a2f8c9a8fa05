"""Recovery steps: which attempt of a compiled problem's retry chain runs first there
(issue #14, the lane change's worst steps).

On the slack problems (5.15)/(6.15) of Algorithms 5.2 and 6.4 while the state is outside the
robust safe set (``h_r > 0``), the SQP attempts of the emittable chain fail with
``Search_Direction_Becomes_Too_Small`` (an l1-merit line search that accepts a rejected
step) after hundreds of iterations, and the chain's interior-point last resort answers.
Measured in session 12 (docs/vehicles.md, "The slow first steps, traced"): one failing SQP
attempt costs 150–240 ms, the interior-point solver alone, cold, 21–50 ms on the same NLPs.
A controller therefore names a *recovery target* (a preset, e.g. ``"recovery"``): on its
recovery steps the attempt of the chain that runs this target's solver leads, from its cold
start, and the rest of the chain follows as usual
(:meth:`~balustrade.backends.casadi_backend.CasadiCompiled.solve`'s ``lead``). The emitted C
runs the same order (``bal/problem.c``'s ``P_solve_lead``), so C = Python holds by
construction.

The lead is an attempt the chain already has: no solver is added, only the order of one
solve changes. When the led interior-point attempt ends at its *acceptable* level, the
solve is ``optimal_inaccurate`` (used, flagged ``uncertified``), in Python and in the emitted
C alike (the C reads IPOPT's own return status: :data:`balustrade.backends.emittable.
ACCEPTABLE_STOP`; docs/vehicles.md, session 13).
"""

from __future__ import annotations

from balustrade.backends.targets import Target, _plain, target
from balustrade.errors import SolverError

#: the recovery target of Algorithms 5.2 and 6.4 by default (a preset name)
RECOVERY_TARGET: str | None = "recovery"


def check_recovery_target(recovery: Target | str | None, what: str) -> Target | str | None:
    """``recovery`` unchanged when it is ``None`` or names a target; a bad value raises the
    :class:`~balustrade.errors.SolverError` of :func:`target`, prefixed with ``what``, at
    construction instead of inside a later ``step`` (review, session 13)."""
    if recovery is None:
        return None
    try:
        target(recovery)
    except SolverError as exc:  # the same error, naming the argument
        raise SolverError(f"{what}: recovery_target: {exc}") from exc
    return recovery


def recovery_lead(compiled: object, recovery: Target | str | None) -> int | None:
    """The index in ``compiled.retries`` of the attempt a recovery step runs first: the
    retry whose solver and option overrides are those of ``recovery`` (a target or preset
    name). ``None`` (the chain in its usual order) when ``recovery`` is ``None``, when
    ``compiled`` is not a CasADi problem with a retry chain, when its chain already starts
    with that solver (its first attempt is the lead), when it has a budget (no retries:
    the time bound) or when no retry matches."""
    if recovery is None:
        return None
    rec = target(recovery)
    retries = getattr(compiled, "retries", None)
    if rec.backend != "casadi" or getattr(compiled, "backend", None) != "casadi" or not retries:
        return None
    if getattr(compiled, "budget", None) is not None:
        return None
    solver = rec.nlp_solver
    if getattr(compiled, "solver_name", None) == solver:
        return None
    for k, (name, overrides) in enumerate(retries):
        if name == solver and _plain(overrides) == rec.solver_options():
            return k
    return None


__all__ = ["RECOVERY_TARGET", "check_recovery_target", "recovery_lead"]
