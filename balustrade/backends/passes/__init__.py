"""Lowering as a visible chain of small passes (DESIGN.md, "Models to learn from").

Each pass (:class:`~balustrade.backends.passes.base.Pass`) has ``accepts``/``apply``/
``invert``; every backend runs one chain, written here and nowhere else:

* CasADi — ``OCP`` →(:class:`~.epigraph.Epigraph`: norm/max cost terms become epigraph
  variables and rows, the layout is extended)→ ``SmoothProblem`` →(:class:`~.casadi_nlp.
  CasadiNLP`)→ ``NLPData`` for ``nlpsol``;
* cvxpy — ``OCP`` →(:class:`~.classify.Classify`: each block row and cost term is split
  into affine, convex quadratic or jointly quadratic pieces, or refused naming the block)→
  ``ClassifiedProblem`` →(:class:`~.to_cvxpy.ToCvxpy`: DPP-parametrized atoms, bounds and
  large rows set aside)→ ``CvxpyProgram``;
* direct — ``OCP`` →(:class:`~.classify.Classify`)→ ``ClassifiedProblem`` →(:class:`~.to_conic.
  ToConic`: constant ``P``, ``A`` and cones, parameter-affine ``q``, ``b``)→ ``ConicProgram``
  for Clarabel/PIQP's own interfaces.

A backend keeps the inverse data of its chain to map a solver's point back to the user's
variables (:func:`~.base.invert_chain`).
"""

from __future__ import annotations

from balustrade.backends.passes.base import Pass, invert_chain, run_chain
from balustrade.backends.passes.casadi_nlp import CasadiNLP
from balustrade.backends.passes.classify import Classify
from balustrade.backends.passes.epigraph import Epigraph
from balustrade.backends.passes.to_conic import ToConic
from balustrade.backends.passes.to_cvxpy import ToCvxpy

#: OCP → SmoothProblem → NLPData (the CasADi backend)
CASADI_CHAIN: tuple[Pass, ...] = (Epigraph(), CasadiNLP())
#: OCP → ClassifiedProblem → CvxpyProgram (the cvxpy backend)
CVXPY_CHAIN: tuple[Pass, ...] = (Classify(), ToCvxpy())
#: OCP → ClassifiedProblem → ConicProgram (the direct backend)
DIRECT_CHAIN: tuple[Pass, ...] = (Classify(), ToConic())

__all__ = ["CASADI_CHAIN", "CVXPY_CHAIN", "DIRECT_CHAIN", "CasadiNLP", "Classify", "Epigraph",
           "Pass", "ToConic", "ToCvxpy", "invert_chain", "run_chain"]
