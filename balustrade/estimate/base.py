"""The loop every parameter-set estimator shares (Assumption 4.2, SPEC §2.19).

:meth:`SetEstimator.update` takes one transition ``(x_{k−1}, u_{k−1}) → x_k``, asks the
estimator for a new set (:meth:`SetEstimator.propose`), and keeps it only if it is contained
in Θ_{k−1} (checked by LPs/support functions, :func:`~.containment.contained_in`); an empty
``Δ_k ∩ Θ_{k−1}`` (data inconsistent with W or Θ₀), a failed LP or a non-nested proposal
keep Θ_{k−1} and say why. It never raises for data: a closed loop keeps running on the last
valid set. With ``check_true=θ*`` (tests, simulations) it also records ``θ* ∈ Θ_k``.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np

from balustrade._checks import as_vector
from balustrade.dsl.sets import Box, Polytope
from balustrade.dsl.system_parametric import ParametricLinearSystem
from balustrade.errors import BalustradeError, ShapeError
from balustrade.estimate.containment import bounding_box, contained_in
from balustrade.estimate.nonfalsified import (
    HalfSpaces,
    delta_rows,
    disturbance_rows,
    model_stack,
)
from balustrade.estimate.records import UpdateRecord, UpdateStatus


@dataclass
class Transition:
    """One observed transition and its non-falsified set Δ_k (4.7)."""

    x_prev: np.ndarray
    u_prev: np.ndarray
    x_next: np.ndarray
    delta: HalfSpaces


@dataclass
class Proposal:
    """What an estimator proposes: a set (or ``None`` with a ``status`` saying why), and the
    LPs it solved."""

    theta: Polytope | None
    lps: int = 0
    status: UpdateStatus = UpdateStatus.UPDATED
    reason: str = ""
    extra: dict = field(default_factory=dict)


class SetEstimator(ABC):
    """Base of the set-membership estimators: holds ``Theta`` (the current set Θ_k), ``k``
    and ``history`` (one :class:`~.records.UpdateRecord` per update). Subclasses implement
    :meth:`propose`."""

    #: tolerance of the nesting and θ* ∈ Θ_k checks
    tol = 1e-9

    def __init__(self, system: ParametricLinearSystem, W: Polytope, Theta0: Polytope,
                 name: str = "estimator"):
        if not isinstance(system, ParametricLinearSystem):
            raise BalustradeError(f"{name}: system must be a ParametricLinearSystem, got "
                                  f"{type(system).__name__}")
        if not isinstance(Theta0, Polytope):
            raise BalustradeError(f"{name}: Theta0 must be a Polytope or Box, got "
                                  f"{type(Theta0).__name__}")
        if Theta0.dim != system.q:
            raise ShapeError(f"{name}: Theta0", f"dimension {system.q} (q, the parameters of "
                             f"{system.name})", f"dimension {Theta0.dim}", what="")
        if not Theta0.is_bounded():
            raise BalustradeError(f"{name}: Theta0 must be bounded (a box or polytope), got "
                                  f"{Theta0!r}")
        self.name = name
        self.system, self.W, self.Theta0 = system, W, Theta0
        self._Hw = disturbance_rows(system, W)
        self._stack = model_stack(system)          # A₀x + B₀u and D(x, u) in one product
        self.Theta: Polytope = Theta0
        self.k = 0
        self.history: list[UpdateRecord] = []

    # -- to implement ------------------------------------------------------------------
    @abstractmethod
    def propose(self, Theta_prev: Polytope, data: Transition) -> Proposal:
        """A new set from Θ_{k−1} and the transition (``None`` + status if none)."""

    # -- the loop ------------------------------------------------------------------------
    def update(self, x_prev: object, u_prev: object, x_next: object,
               check_true: object | None = None) -> Polytope:
        """One update Θ_{k−1} → Θ_k; returns Θ_k and appends its record to ``history``."""
        sys = self.system
        x_prev = as_vector(x_prev, f"{self.name}.update: x_prev", sys.nx)
        u_prev = as_vector(u_prev, f"{self.name}.update: u_prev", sys.nu)
        x_next = as_vector(x_next, f"{self.name}.update: x_next", sys.nx)
        theta_true = (None if check_true is None
                      else as_vector(check_true, f"{self.name}.update: check_true", sys.q))
        delta = delta_rows(self._stack, self._Hw, self.W.h, x_prev, u_prev, x_next)  # (4.7)
        prev = self.Theta
        prop = self.propose(prev, Transition(x_prev, u_prev, x_next, delta))
        lps, status, reason = prop.lps, prop.status, prop.reason
        accepted, nested = False, True
        if prop.theta is not None:
            check = contained_in(prop.theta, prev, self.tol)
            lps += check.lps
            nested = check.nested
            if nested:
                accepted, status = True, UpdateStatus.UPDATED
            else:
                status, reason = UpdateStatus.NOT_NESTED, check.reason
        elif status is UpdateStatus.UPDATED:
            status = UpdateStatus.NO_UPDATE
        if accepted:
            self.Theta = prop.theta  # type: ignore[assignment]
        lb, ub, box_lps, _ = bounding_box(self.Theta)
        contains = (None if theta_true is None
                    else bool(np.all(self.Theta.H @ theta_true - self.Theta.h <= self.tol)))
        self.k += 1
        self.history.append(UpdateRecord(self.k, status, accepted, nested, contains,
                                         lps + box_lps, lb, ub, reason))
        return self.Theta

    def assumption_4_2_held(self) -> bool:
        """Every record so far has ``θ* ∈ Θ_k ⊆ Θ_{k−1}`` (records without θ* only need
        nesting of what was accepted)."""
        return all(r.assumption_4_2 is not False and (r.nested or not r.accepted)
                   for r in self.history)

    def reset(self) -> None:
        """Back to Θ₀ with an empty history."""
        self.Theta, self.k, self.history = self.Theta0, 0, []


def require_box(Theta0: Polytope, name: str) -> Box:
    """Θ₀ as a bounded :class:`~balustrade.dsl.sets.Box` (fixed-shape box updates)."""
    if not isinstance(Theta0, Box) or not Theta0.is_bounded():
        raise BalustradeError(f"{name}: Theta0 must be a bounded Box for this update, got "
                              f"{type(Theta0).__name__}")
    return Theta0


__all__ = ["Proposal", "SetEstimator", "Transition", "require_box"]
