"""Set-membership parameter estimation (thesis Chapter 4, (4.7), SPEC §2.19).

A new layer: it imports the language (:mod:`balustrade.dsl`), the LPs of
:mod:`balustrade.backends.lp` (the backends name the solver), ``errors`` and ``_checks``.
Every estimator keeps Assumption 4.2 — ``θ* ∈ Θ_k ⊆ Θ_{k−1}`` — checked and recorded at
every step, and never raises for data that falsify the model (it keeps Θ_{k−1}).
"""

from balustrade.estimate.base import Proposal, SetEstimator, Transition
from balustrade.estimate.containment import Containment, bounding_box, contained_in
from balustrade.estimate.nested import NestedEstimator, SetProposer
from balustrade.estimate.nonfalsified import HalfSpaces, disturbance_rows, nonfalsified_set
from balustrade.estimate.records import UpdateRecord, UpdateStatus
from balustrade.estimate.updates import (
    BoxUpdate,
    ExactUpdate,
    FixedShapeUpdate,
    HypercubeUpdate,
    hypercube_centre,
    remove_redundant,
)

__all__ = [
    "BoxUpdate", "Containment", "ExactUpdate", "FixedShapeUpdate", "HalfSpaces",
    "HypercubeUpdate", "NestedEstimator", "Proposal", "SetEstimator", "SetProposer",
    "Transition", "UpdateRecord", "UpdateStatus", "bounding_box", "contained_in",
    "disturbance_rows", "hypercube_centre", "nonfalsified_set", "remove_redundant",
]
