"""Closed-loop algorithms: one interface (``step(x, u_p) -> u, info``) and ``simulate``."""

from balustrade.control.base import Controller, StepInfo, Trace, simulate
from balustrade.control.fallbacks import project
from balustrade.control.mpc import MPCController
from balustrade.control.pcbf import PCBFSafetyFilter
from balustrade.control.plant import ContinuousPlant
from balustrade.control.rapsf import RAPSF

__all__ = ["ContinuousPlant", "Controller", "MPCController", "PCBFSafetyFilter", "StepInfo",
           "Trace", "project", "simulate"]
__all__ += ["RAPSF"]
