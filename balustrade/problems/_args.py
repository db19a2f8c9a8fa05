"""Validation of the formulation builders' arguments, before any block is built.

Every builder of :mod:`balustrade.problems` calls these first so that a bad argument is
refused with the builder's name, the argument's name and what was expected (DESIGN.md
principle 5) instead of surfacing later as a NaN bound or a wrong value function.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from balustrade._checks import (
    as_scalar,
    check_callable,
    check_deltas,
    check_horizon,
    check_instance,
    check_norm_order,
    check_weight,
)
from balustrade.dsl.sets import Polytope, Set
from balustrade.dsl.system import System
from balustrade.errors import ShapeError

_SKIP = object()


def check_system_sets(block: str, system: object, X: object = _SKIP, U: object = _SKIP,
                      polytope: bool = False, Xf: object = _SKIP) -> None:
    """``system`` is a System; the sets given (``X``, ``Xf``: state sets, ``U``: input set;
    ``None`` is refused, leave an argument out to skip it) are sets (polytopes if
    ``polytope``) of the system's state and input dimensions."""
    check_instance(system, System, f"{block}: system")
    kind = Polytope if polytope else Set
    for label, S, dim in (("X", X, system.nx), ("U", U, system.nu), ("Xf", Xf, system.nx)):
        if S is _SKIP:
            continue
        check_instance(S, kind, f"{block}: {label}")
        if S.dim != dim:
            raise ShapeError(f"{block}: {label} ({S.name})", f"dimension {dim}",
                             f"dimension {S.dim}")


def check_pcbf_args(block: str, system: object, X: object, U: object, h_f: Callable,
                    N: object, deltas: object, polytope: bool = False
                    ) -> tuple[int, np.ndarray]:
    """The arguments shared by the PCBF problems (2.23), (2.24), (5.15), (6.15), (7.8):
    sets of the right dimensions, a callable ``h_f``, ``N >= 1`` and ``N`` finite
    nonnegative tightenings."""
    check_system_sets(block, system, X, U, polytope)
    check_callable(h_f, f"{block}: h_f")
    N = check_horizon(N, block)
    return N, check_deltas(deltas, N, block)


def check_weights(block: str, n: int, m: int, Q: object, R: object, P: object
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stage and terminal weights: ``Q, P`` of shape ``(n, n)``, ``R`` ``(m, m)``, all PSD."""
    return (check_weight(Q, n, f"{block}: Q"), check_weight(R, m, f"{block}: R"),
            check_weight(P, n, f"{block}: P"))


def positive(value: object, block: str) -> float:
    """A finite number ``> 0`` (``α_f``, a penalty)."""
    return as_scalar(value, block, low=0.0, low_open=True)


def nonnegative(value: object, block: str) -> float:
    """A finite number ``>= 0`` (a margin ``eps``, a level)."""
    return as_scalar(value, block, low=0.0)


__all__ = ["check_norm_order", "check_pcbf_args", "check_system_sets", "check_weights",
           "nonnegative", "positive"]
