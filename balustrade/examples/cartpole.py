"""The cart-pole PCBF example (issue #14, nonlinear case): the terminal CBF from the
linearization at the upright equilibrium and the PCBF pair (2.24)+(2.23) on the nonlinear
RK4 model (:mod:`balustrade.models.cartpole`), ``N = 20``.

Scenario (:func:`cartpole_scenario`): the pole starts tilted, ``x_0 = (0, 0.15, 0, 0)``, and
the proposal :func:`destabilizing_proposal` pushes the cart to the right end of the track
with a force that also drives the pole over: unfiltered, the state leaves ``X`` within
~0.4 s; the filter keeps it in ``X`` and applies the proposal whenever that is safe.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from balustrade.backends import Compiled, Target, compile
from balustrade.design.terminal_cbf import synthesize_terminal_cbf
from balustrade.dsl.sets import Box
from balustrade.dsl.system import System
from balustrade.models.cartpole import cartpole, cartpole_setup
from balustrade.problems.pcbf import pcbf_filter_problem, pcbf_slack_problem
from balustrade.problems.terminal_cbf import TerminalCBF

#: reserve level of the terminal CBF SDP (``min_level``): the volume-maximal ellipsoid is
#: input-limited for this model, so ``γ_f`` would otherwise collapse to 0
MIN_LEVEL = 0.5
#: the tilted initial state of the scenario
X0 = np.array([0.0, 0.15, 0.0, 0.0])


@dataclass
class CartpoleDesign:
    system: System
    X: Box
    U: Box
    h_f: TerminalCBF
    N: int
    deltas: np.ndarray
    alpha_f: float


def cartpole_design(N: int = 20) -> CartpoleDesign:
    """The model, sets and the terminal CBF (7.11)/(6.17) of the linearization at 0."""
    system, s = cartpole(), cartpole_setup(N)
    A, B = system.jacobians(np.zeros(4), np.zeros(1))
    h_f = synthesize_terminal_cbf(A, B, s.X, s.U, delta_N=s.deltas[-1], min_level=MIN_LEVEL)
    return CartpoleDesign(system, s.X, s.U, h_f, s.N, s.deltas, s.alpha_f)


def cartpole_problems(target: Target | str = "fast-sqp", N: int = 20,
                      design: CartpoleDesign | None = None) -> tuple[Compiled, Compiled]:
    """(2.24) (slack norm 1) and (2.23) for the cart-pole, compiled for ``target``."""
    d = cartpole_design(N) if design is None else design
    args = (d.system, d.X, d.U, d.h_f, d.N, d.deltas)
    slack = compile(pcbf_slack_problem(*args, alpha_f=d.alpha_f, slack_norm=1), target)
    filt = compile(pcbf_filter_problem(*args), target)
    return slack, filt


def destabilizing_proposal(x: np.ndarray, k: int) -> np.ndarray:
    """A proposal that drives the cart toward ``p = +1`` and the pole over: a constant
    push of 8 N with a positive feedback on the angle."""
    x = np.asarray(x, dtype=float).reshape(-1)
    return np.array([8.0 + 20.0 * x[1]])


def cartpole_scenario() -> tuple[np.ndarray, object]:
    """``(x_0, proposal)`` of the closed-loop example."""
    return X0.copy(), destabilizing_proposal


__all__ = ["CartpoleDesign", "X0", "cartpole_design", "cartpole_problems",
           "cartpole_scenario", "destabilizing_proposal"]
