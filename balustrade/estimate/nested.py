"""Any estimator made to satisfy Assumption 4.2's nesting (SPEC §2.19, "non-nested
estimators, e.g. Bayesian confidence sets: accept a new set only if it is contained in the
previous one").

:class:`NestedEstimator` wraps either another :class:`~.base.SetEstimator` (its
:meth:`~.base.SetEstimator.propose` is used, from the set the wrapper has accepted) or any
object with ``propose(Theta_prev, x_prev, u_prev, x_next) -> Polytope | None``; each
proposal is checked by support functions against Θ_{k−1} and refused — Θ_{k−1} kept, the
reason recorded — when it is not contained in it.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from balustrade.dsl.sets import Polytope
from balustrade.dsl.system_parametric import ParametricLinearSystem
from balustrade.errors import BalustradeError
from balustrade.estimate.base import Proposal, SetEstimator, Transition
from balustrade.estimate.records import UpdateStatus


@runtime_checkable
class SetProposer(Protocol):
    """An outside estimator: a candidate set from the accepted Θ_{k−1} and one transition
    (``None``: no new set this step)."""

    def propose(self, Theta_prev: Polytope, x_prev: object, u_prev: object,
                x_next: object) -> Polytope | None: ...


class NestedEstimator(SetEstimator):
    """Accepts the wrapped estimator's set only if ``Θ_new ⊆ Θ_{k−1}``; otherwise keeps
    Θ_{k−1} and records ``not_nested`` with the violated row and by how much."""

    def __init__(self, inner: SetEstimator | SetProposer,
                 system: ParametricLinearSystem | None = None, W: Polytope | None = None,
                 Theta0: Polytope | None = None, name: str = "nested"):
        if isinstance(inner, SetEstimator):
            system = inner.system if system is None else system
            W = inner.W if W is None else W
            Theta0 = inner.Theta0 if Theta0 is None else Theta0
        elif not isinstance(inner, SetProposer):
            raise BalustradeError(f"{name}: inner must be a SetEstimator or have "
                                  f"propose(Theta_prev, x_prev, u_prev, x_next), got "
                                  f"{type(inner).__name__}")
        if system is None or W is None or Theta0 is None:
            raise BalustradeError(f"{name}: an outside estimator needs system, W and Theta0")
        super().__init__(system, W, Theta0, name=name)
        self.inner = inner

    def propose(self, Theta_prev: Polytope, data: Transition) -> Proposal:
        if isinstance(self.inner, SetEstimator):
            self.inner.k = self.k
            return self.inner.propose(Theta_prev, data)
        try:
            new = self.inner.propose(Theta_prev, data.x_prev, data.u_prev, data.x_next)
        except BalustradeError as exc:  # an empty candidate set, say: keep Θ_{k−1}
            return Proposal(None, 0, UpdateStatus.FAILED, f"inner estimator: {exc}")
        if new is None:
            return Proposal(None, 0, UpdateStatus.NO_UPDATE, "inner estimator proposed none")
        if not isinstance(new, Polytope) or new.dim != self.system.q:
            return Proposal(None, 0, UpdateStatus.FAILED,
                            f"inner estimator returned {type(new).__name__}, not a Polytope "
                            f"of dimension {self.system.q}")
        return Proposal(new, 0)


__all__ = ["NestedEstimator", "SetProposer"]
