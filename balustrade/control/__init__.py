"""Closed-loop algorithms: one interface (``step(x, u_p) -> u, info``) and ``simulate``."""

from balustrade.control.base import Controller, StepInfo, Trace, simulate
from balustrade.control.fallbacks import project
from balustrade.control.pcbf import PCBFSafetyFilter

__all__ = ["Controller", "PCBFSafetyFilter", "StepInfo", "Trace", "project", "simulate"]
