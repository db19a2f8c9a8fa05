"""A receding-horizon controller for any compiled horizon problem (MPC (2.9) and its
engineering variants: rate limits, rate costs, reference tracking).

At each sample it solves the compiled problem with ``x0 = x_k``, the previous applied input
``u_prev = u_{k−1}`` (when the problem declares it, e.g. through
:func:`balustrade.dsl.rates.rate_limit`) and the other parameters (fixed, or a function of
the step ``k`` and the state, e.g. a moving reference), and applies ``u_{0|k}``::

    ctl = MPCController(compile(ocp, "fast-sqp"), parameters=lambda k, x: {"x_ref": r(k)})
    trace = simulate(plant, ctl, x0, 100)

It owns the previous input: the first step uses ``u_init`` (zero by default), each later one
the input applied last, so the rate limits hold across samples. The proposal ``u_p`` of the
common interface is not used (MPC computes its own input). A failed solve never raises:
the controller applies the next input of the last plan (``fallback="shifted_plan"``), or,
when that plan is used up, holds the previous input (``fallback="hold"``) — both respect
the rate limits the plan was computed with.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np

from balustrade._checks import as_vector
from balustrade.control.base import StepInfo, note_solve
from balustrade.control.fallbacks import finite_state
from balustrade.errors import BalustradeError

Parameters = Mapping[str, object] | Callable[[int, np.ndarray], Mapping[str, object]] | None


class MPCController:
    """``step(x, u_p) -> (u_{0|k}, StepInfo)`` for a compiled problem with an initial-state
    parameter (``state``, default ``"x0"``) and an input variable (``input``, ``"u"``)."""

    def __init__(self, compiled: object, parameters: Parameters = None, state: str = "x0",
                 previous_input: str = "u_prev", input: str = "u",
                 u_init: object | None = None, name: str = "mpc"):
        ocp = getattr(compiled, "ocp", None)
        if ocp is None or not callable(getattr(compiled, "solve", None)):
            raise BalustradeError(f"{name}: expected a compiled problem (balustrade.compile), "
                                  f"got {type(compiled).__name__}")
        if state not in ocp.parameters:
            raise BalustradeError(f"{name}: {ocp.name} has no initial-state parameter "
                                  f"{state!r}; declared: {list(ocp.parameters)}")
        if input not in ocp.variables:
            raise BalustradeError(f"{name}: {ocp.name} has no input variable {input!r}")
        if not (parameters is None or callable(parameters) or isinstance(parameters, Mapping)):
            raise BalustradeError(f"{name}: parameters must be a dict or a function (k, x) -> "
                                  f"dict, got {type(parameters).__name__}")
        self.compiled, self.ocp, self.name = compiled, ocp, name
        self.state, self.input = state, input
        self.nx = ocp.parameters[state].shape[0]
        self.nu = ocp.variables[input].shape[0]
        self.previous_input = previous_input if previous_input in ocp.parameters else None
        self.parameters = parameters
        self.u_init = np.zeros(self.nu) if u_init is None else \
            as_vector(u_init, f"{name}: u_init", self.nu)
        self.reset()

    def reset(self) -> None:
        """Back to step 0: the previous input is ``u_init`` and there is no plan."""
        self.k = 0
        self.u_prev = self.u_init.copy()
        self._plan: np.ndarray | None = None
        self._age = 0  # samples since the plan was computed
        self._last = None

    def step(self, x: np.ndarray, u_p: np.ndarray | None = None) -> tuple[np.ndarray, StepInfo]:
        xk = finite_state(x, self.nx, f"{self.name}.step: x")
        if u_p is not None:  # not used by the MPC law, but a wrong one is the caller's error
            as_vector(u_p, f"{self.name}.step: u_p", self.nu, finite=False)
        info = StepInfo()
        sol = None
        if xk is None:
            info.status = "non_finite_state"
        else:
            sol = self.compiled.solve(self._params(xk), warm_start=self._last)
            info.status, info.solve_time = sol.status, sol.solve_time
            info.solutions[self.name] = sol
            note_solve(info, self.name, sol.status)
        if sol is not None and sol.usable:
            self._plan, self._age, self._last = np.asarray(sol[self.input]).reshape(
                self.nu, -1), 0, sol
            info.values["objective"] = float(sol.objective)
        else:
            self._age += 1
            self._last = None
        if self._plan is not None and self._age < self._plan.shape[1]:
            u = self._plan[:, self._age].copy()
            if self._age:
                info.fallback = "shifted_plan"
        else:
            u = self.u_prev.copy()
            info.fallback = "hold"
        self.u_prev, self.k = u, self.k + 1
        return u, info

    def _params(self, x: np.ndarray) -> dict[str, object]:
        extra = self.parameters
        if callable(extra):
            try:
                extra = extra(self.k, x)
            except Exception as exc:  # the user's function failed: a programming error
                raise BalustradeError(f"{self.name}: parameters(k, x) failed at step {self.k}: "
                                      f"{type(exc).__name__}: {exc}") from exc
        if not (extra is None or isinstance(extra, Mapping)):
            raise BalustradeError(f"{self.name}: parameters(k, x) must return a dict, got "
                                  f"{type(extra).__name__} at step {self.k}")
        params = dict(extra or {})
        params[self.state] = x
        if self.previous_input is not None:
            params[self.previous_input] = self.u_prev
        return params
