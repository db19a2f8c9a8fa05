"""The structured interior-point solver's stall stop: a run whose scaled optimality error stays
at most ``tol_acceptable`` for ``acceptable_iter`` consecutive iterations without meeting its
tolerance stops as ``StopAtAcceptablePoint``. That stop is a *failure* in Python
(``casadi_backend._FATROP_FLAGS``) and in the emitted C (fatrop returns nonzero unless
``Success``), so a retry chain goes on to its next attempt instead of iterating on.

Session 14 (docs/obstacles.md): on the §8.3 obstacle PCBF, fatrop stalled at a degenerate
point for 301 iterations (from (−0.5, −1.5), step 48); with ``(1e-3, 20)`` it stops after ~32
and the chain's IPOPT attempt from the certified plan answers with the same input. Measured
there: on the 5 reference loops and 200 cold states no other attempt changed
(``acceptable_iter`` 15, 20, 30 and tolerances 1e-4 … 1e-2 alike); ``acceptable_iter`` 10 cut
a warm solve that converges in 37 iterations.

This module names fatrop because solver names and options belong to ``backends/`` (issue
#13); code elsewhere asks for "the stall stop" of a target.
"""

from __future__ import annotations

import numpy as np

from balustrade.backends.casadi_backend import DEFAULT_OPTIONS
from balustrade.backends.targets import Target
from balustrade.backends.targets import target as resolve_target
from balustrade.errors import BalustradeError

#: ``(tol_acceptable, acceptable_iter)`` of fatrop 1.1.8 (module docstring)
STALL_STOP: tuple[float, int] = (1e-3, 20)


def check_stall_stop(stall: object, name: str = "stall_stop") -> tuple[float, int] | None:
    """``stall`` as ``None`` or ``(tol_acceptable, acceptable_iter)``; anything else → a
    :class:`~balustrade.errors.BalustradeError` naming ``name``."""
    if stall is None:
        return None
    ok = isinstance(stall, tuple | list) and len(stall) == 2
    if ok:
        tol, iters = stall
        ok = (isinstance(tol, int | float) and not isinstance(tol, bool)
              and bool(np.isfinite(tol)) and tol > 0 and isinstance(iters, int | np.integer)
              and not isinstance(iters, bool) and iters >= 1)
    if not ok:
        raise BalustradeError(f"{name} must be None or (tol_acceptable > 0, acceptable_iter "
                              f">= 1), got {stall!r}")
    return float(stall[0]), int(stall[1])


def with_stall_stop(target: Target | str, stall: tuple[float, int] | None = STALL_STOP
                    ) -> Target | str:
    """``target`` (a preset name or a :class:`~balustrade.backends.targets.Target`) with the
    stall stop ``stall = (tol_acceptable, acceptable_iter)`` when its solver is fatrop (its
    other fatrop options kept; a chain's cold fatrop retry shares the solver, hence the stop);
    any other target, or ``stall=None``, is returned as given."""
    stall = check_stall_stop(stall)
    if stall is None:
        return target
    t = resolve_target(target)
    if t.backend != "casadi" or t.solver != "fatrop":
        return target
    fat = {**DEFAULT_OPTIONS["fatrop"]["fatrop"], **dict(t.options.get("fatrop", {})),
           "tol_acceptable": stall[0], "acceptable_iter": stall[1]}
    return t.with_options({"fatrop": fat})


__all__ = ["STALL_STOP", "check_stall_stop", "with_stall_stop"]
