"""Regret-optimal control synthesized by semidefinite programs (thesis Chapter 3).

``LTVSystem`` + ``build_operators`` give the stacked operators of the system level
parametrization; the builders of :mod:`.synthesis` state (3.19), (3.24), (3.28), (3.30),
(3.32), (3.34) and the SH2/SH∞ baselines as structured SDPs (data, no solver);
:mod:`balustrade.control.regret_synthesis` solves and certifies them (``dynamic_regret`` …);
:class:`~balustrade.control.regret.RegretController` runs the result in closed loop;
:mod:`.verify` certifies worst-case regret independently of the SDP solver.
"""

from balustrade.errors import moved_names
from balustrade.problems.regret.operators import (
    LTVSystem,
    Operators,
    build_operators,
    controller_from_responses,
    responses_from_controller,
)
from balustrade.problems.regret.synthesis import (
    MOVED_SOLVERS,
    RegretProblem,
    StateInputConstraints,
    adversarial_regret_problem,
    dynamic_regret_problem,
    generalized_regret_problem,
    h2_problem,
    hinf_problem,
    pointwise_dynamic_problem,
    pointwise_regret_problem,
    zero_x0_regret_problem,
)

__all__ = [
    "LTVSystem", "Operators", "RegretProblem", "build_operators",
    "controller_from_responses", "responses_from_controller", "StateInputConstraints",
    "adversarial_regret_problem", "dynamic_regret_problem", "generalized_regret_problem",
    "h2_problem", "hinf_problem", "pointwise_dynamic_problem", "pointwise_regret_problem",
    "zero_x0_regret_problem",
]

#: names that moved out of this package (issue #13): deprecated aliases (errors.moved_names)
__getattr__ = moved_names(__name__, {**MOVED_SOLVERS,
                                     "RegretController": "balustrade.control.regret",
                                     "Rollout": "balustrade.control.regret"})
