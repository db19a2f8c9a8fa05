"""Reference implementation of Algorithm 7.5 for the tests (not collected: no ``test_``).

:class:`~balustrade.control.approximate.ApproximatePCBFFilter` solves (7.6) and (7.5) on a
fast path (buffered evaluations, the KKT-vertex start, :class:`FastNLP` first attempts).
The tests compare it with this reference, which solves every local (7.6) problem and every
(7.5) through ``Compiled.solve`` and its retry chain. It used to be the controller's
``fast=False`` flag; it exists only to test the fast path, so it lives with the tests.
"""

from __future__ import annotations

import inspect

import numpy as np

from balustrade.control.approximate import ApproximatePCBFFilter
from balustrade.control.base import StepInfo
from balustrade.problems.approximate import DecreaseResult, MaximalDecrease


class ReferenceApproximatePCBFFilter(ApproximatePCBFFilter):
    """Algorithm 7.5 with every solve through ``Compiled.solve`` (same arguments as
    :class:`~balustrade.control.approximate.ApproximatePCBFFilter`)."""

    def __init__(self, *args: object, **kwargs: object):
        super().__init__(*args, **kwargs)
        bound = inspect.signature(ApproximatePCBFFilter).bind(*args, **kwargs)
        bound.apply_defaults()
        a = bound.arguments
        self.decrease = MaximalDecrease(self.system, self.U, self.h, a["solver"], a["options"],
                                        a["grid_points"], a["n_local"], fast=False)
        self._h_next = self.decrease._h_next

    def _filter(self, x: np.ndarray, u_p: np.ndarray, dec: DecreaseResult,
                info: StepInfo) -> tuple[np.ndarray | None, str]:
        return self._filter_compiled(x, u_p, dec, info)
