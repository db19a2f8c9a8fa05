"""Regret-optimal control synthesized by semidefinite programs (thesis Chapter 3).

``LTVSystem`` + ``build_operators`` give the stacked operators of the system level
parametrization; the functions of :mod:`.synthesis` solve (3.19), (3.24), (3.28), (3.30),
(3.32), (3.34) and the SH2/SH∞ baselines;
:class:`~balustrade.control.regret.RegretController` runs the result in closed loop;
:mod:`.verify` certifies worst-case regret independently of the SDP solver.
"""

from balustrade.problems.regret.operators import (
    LTVSystem,
    Operators,
    build_operators,
    controller_from_responses,
    responses_from_controller,
)
from balustrade.problems.regret.synthesis import (
    StateInputConstraints,
    SynthesisResult,
    adversarial_regret,
    dynamic_regret,
    generalized_regret,
    h2,
    hinf,
    pointwise_dynamic_regret,
    pointwise_regret,
    zero_x0_regret,
)

__all__ = [
    "LTVSystem", "Operators", "build_operators",
    "controller_from_responses",
    "responses_from_controller", "StateInputConstraints", "SynthesisResult",
    "adversarial_regret", "dynamic_regret", "generalized_regret", "h2", "hinf",
    "pointwise_dynamic_regret", "pointwise_regret", "zero_x0_regret",
]
