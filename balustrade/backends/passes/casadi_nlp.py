"""The last pass of the CasADi chain: a :class:`~balustrade.backends.passes.epigraph.
SmoothProblem` becomes the data ``nlpsol`` takes (:class:`NLPData`): the ``{x, p, f, g}``
dictionary and the numeric bounds and initial point, all read from the one layout."""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from balustrade.backends.passes.base import Pass
from balustrade.backends.passes.epigraph import SmoothProblem
from balustrade.dsl.layout import Layout


@dataclass(frozen=True)
class NLPData:
    """``nlpsol``'s problem (``nlp``) and its numeric data: bounds on ``x`` and ``g`` and
    the default initial point ``x0`` (the user's ``init``, zeros for added blocks)."""

    nlp: dict
    layout: Layout
    lbx: np.ndarray
    ubx: np.ndarray
    lbg: np.ndarray
    ubg: np.ndarray
    x0: np.ndarray
    block_rows: dict[str, slice]
    n_g_user: int


class CasadiNLP(Pass):
    """SmoothProblem → :class:`NLPData` (nothing to invert: the variables are the same)."""

    name = "casadi-nlp"

    def accepts(self, problem: object) -> bool:
        return isinstance(problem, SmoothProblem)

    def apply(self, sp: SmoothProblem) -> tuple[NLPData, None]:
        lbx, ubx = sp.variables.bounds()
        nlp = {"x": sp.w, "p": sp.p, "f": sp.f, "g": sp.g}
        return NLPData(nlp, sp.variables, lbx, ubx, sp.lbg, sp.ubg, sp.variables.initial(),
                       sp.block_rows, sp.n_g_user), None


def as_dm(data: NLPData) -> dict[str, ca.DM]:
    """The bounds as CasADi ``DM`` (converted once, passed to every solve)."""
    return {k: ca.DM(getattr(data, k)) for k in ("lbx", "ubx", "lbg", "ubg")}
