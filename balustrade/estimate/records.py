"""What an estimator records at every step (Assumption 4.2 checked and kept, SPEC §2.19)."""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np


class UpdateStatus(StrEnum):
    """Outcome of one parameter-set update."""

    #: the proposed set was accepted (it is nested in the previous one)
    UPDATED = "updated"
    #: Δ_k ∩ Θ_{k−1} is empty: the data contradict W or Θ₀; Θ_{k−1} is kept
    FALSIFIED = "falsified"
    #: the proposed set is not contained in Θ_{k−1}; Θ_{k−1} is kept
    NOT_NESTED = "not_nested"
    #: the estimator proposed nothing; Θ_{k−1} is kept
    NO_UPDATE = "no_update"
    #: an LP did not solve to optimality; Θ_{k−1} is kept (never a guessed set)
    FAILED = "failed"


@dataclass(frozen=True)
class UpdateRecord:
    """One step: ``k``, the status, whether the new set was accepted, whether the proposal
    was nested in Θ_{k−1} (checked by LPs/support functions), whether θ* ∈ Θ_k (``None``
    when θ* is not known), the number of LPs solved, the bounding box ``[lb, ub]`` of Θ_k
    after the step, and why a proposal was refused."""

    k: int
    status: UpdateStatus
    accepted: bool
    nested: bool
    contains_true: bool | None
    lps: int
    lb: np.ndarray
    ub: np.ndarray
    reason: str = ""

    @property
    def width(self) -> np.ndarray:
        """``ub − lb`` per parameter."""
        return self.ub - self.lb

    @property
    def volume(self) -> float:
        """Volume of the bounding box of Θ_k (the set's volume for a box)."""
        return float(np.prod(self.width))

    @property
    def assumption_4_2(self) -> bool | None:
        """``θ* ∈ Θ_k ⊆ Θ_{k−1}`` (``None`` when θ* is not known): the set kept is always
        nested, so this is ``contains_true`` unless a proposal was accepted un-nested."""
        if self.contains_true is None:
            return None
        return bool(self.contains_true and (self.nested or not self.accepted))


__all__ = ["UpdateRecord", "UpdateStatus"]
