"""Fallbacks shared by the closed-loop algorithms (DESIGN.md principle 4: never raise in
the loop): the projection of the proposed input onto ``U``, the guard for non-finite
measured states and the one for non-finite proposals.

Bad shapes and types are programming errors and still raise a
:class:`~balustrade.errors.BalustradeError`; NaN or inf *values* are runtime data:

* a non-finite state ``x`` → nothing is solved, ``u_p`` (non-finite entries read as 0)
  projected onto ``U``: status ``"non_finite_state"``, fallback ``"projected_proposal"``
  (:func:`finite_state`, :func:`projected_proposal`);
* a non-finite proposal ``u_p`` with a finite state → its non-finite entries are read as
  0 and the algorithm runs as usual (:func:`finite_proposal`, :func:`note_proposal`), so
  the applied input is still the safety filter's (the certificate of (2.23), (5.16),
  (6.15), Algorithm 7.5 does not depend on ``u_p``, which only enters the cost), rather
  than the projection, which ignores safety. The emitted C steps do the same
  (``<name>_proposal_replaced``).
"""

from __future__ import annotations

import numpy as np

from balustrade._checks import as_vector
from balustrade.control.base import StepInfo
from balustrade.dsl.sets import Set
from balustrade.errors import BalustradeError, NonFiniteError

#: StepInfo.status prefix of a step whose proposal had NaN or inf entries
NON_FINITE_PROPOSAL = "non_finite_proposal"


def finite_state(x: np.ndarray, nx: int | None, block: str) -> np.ndarray | None:
    """``x`` as a checked vector (wrong shapes still raise), or ``None`` if it contains
    NaN or inf, in which case the caller applies :func:`projected_proposal`."""
    try:
        return as_vector(x, block, nx)
    except NonFiniteError:
        return None


def finite_proposal(u_p: object, nu: int, block: str) -> tuple[np.ndarray, int]:
    """``u_p`` as a checked vector of length ``nu`` (wrong shapes and types still raise a
    :class:`~balustrade.errors.BalustradeError`) with its NaN/inf entries replaced by 0,
    and the number of entries replaced (record it with :func:`note_proposal`)."""
    u = as_vector(u_p, block, nu, finite=False)
    bad = ~np.isfinite(u)
    if bad.any():
        u = np.where(bad, 0.0, u)
    return u, int(bad.sum())


def note_proposal(info: StepInfo, replaced: int) -> StepInfo:
    """Record in ``info`` a proposal whose ``replaced`` entries were NaN or inf (read as 0):
    ``status`` becomes ``"non_finite_proposal"`` (a step that was ``"ok"``) or
    ``"non_finite_proposal_<status>"``; ``values["non_finite_proposal"]`` counts them."""
    if replaced:
        info.values["non_finite_proposal"] = float(replaced)
        info.status = NON_FINITE_PROPOSAL if info.status == "ok" else \
            f"{NON_FINITE_PROPOSAL}_{info.status}"
    return info


def projected_proposal(u_p: np.ndarray, U: Set) -> tuple[np.ndarray, StepInfo]:
    """The last-resort fallback for a non-finite state: ``u_p`` projected onto ``U``."""
    return project(u_p, U), StepInfo(status="non_finite_state", fallback="projected_proposal")


def project(u: np.ndarray, U: Set) -> np.ndarray:
    """Euclidean projection onto ``U`` (:meth:`Set.project <balustrade.dsl.sets_base.Set.project>`:
    clipping for boxes, exact for polytopes and ellipsoids); NaN or inf entries of ``u`` are
    read as 0 (as the C steps do); a ``u`` that is not numbers or not of ``U``'s dimension
    raises a :class:`~balustrade.errors.BalustradeError`. A set without a projection (a
    :class:`~balustrade.dsl.sets.FunctionSet`) leaves ``u`` as it is."""
    u = as_vector(u, "project: u", U.dim, finite=False)
    u = np.where(np.isfinite(u), u, 0.0)
    try:
        return U.project(u)
    except BalustradeError:  # no projection onto this kind of set: never raise in the loop
        return u
