"""Causal linear controllers ``u_k = Σ_{j≤k} K_{k,j} x_j`` from the regret synthesis
(thesis Chapter 3, (3.15)) in closed loop.

:class:`RegretController` is a controller like the others of :mod:`balustrade.control`:
``step(x, u_p) -> (u, StepInfo)`` (it keeps the state history the causal law needs; the
proposal is not used — the law is a feedback, not a filter) and ``reset()``.
:func:`rollout` runs it on the LTV system of its operators for ``k = 0..T`` and returns a
:class:`Rollout`: the common :class:`~balustrade.control.base.Trace` plus the cost ``J``
(3.3), the non-causal optimum ``J*`` (3.6) and the constraint violation.
``RegretController.simulate(x0, w)`` is the short form.

The synthesis problems (3.19)–(3.41) are stated in :mod:`balustrade.problems.regret` and
solved and certified by :mod:`balustrade.control.regret_synthesis`, whose results give the
gain (:meth:`RegretController.from_result`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from balustrade._checks import as_matrix, as_vector
from balustrade.control.base import StepInfo, Trace
from balustrade.errors import BalustradeError, ShapeError
from balustrade.problems.regret.operators import Operators


@dataclass(frozen=True)
class Rollout:
    """One closed-loop run of a causal controller over the horizon ``T``.

    ``trace`` holds ``T + 1`` states and ``T + 1`` inputs (``u_T`` enters the cost (3.3)
    only) and the ``T`` disturbances; ``J`` is the cost (3.3), ``J_star`` the non-causal
    optimum (3.6) for the same ``(x_0, w)``, ``violation`` ``max(Hz − 1)`` over the run when
    constraints were given (``None`` otherwise)."""

    trace: Trace
    J: float
    J_star: float
    violation: float | None

    @property
    def x(self) -> np.ndarray:
        """States ``(T+1, n)``."""
        return self.trace.states

    @property
    def u(self) -> np.ndarray:
        """Inputs ``(T+1, m)``."""
        return self.trace.inputs

    @property
    def w(self) -> np.ndarray:
        """Disturbances ``(T, p)``."""
        return self.trace.disturbances

    @property
    def regret(self) -> float:
        return self.J - self.J_star

    @property
    def ratio(self) -> float:
        """J / J* (competitive ratio of this run, (3.10))."""
        return self.J / self.J_star if self.J_star > 0 else float("inf")

    @property
    def satisfied(self) -> bool:
        return self.violation is None or self.violation <= 1e-7


class RegretController:
    """The causal state-feedback law (3.15) with its responses ``Φ_u`` (for reference)."""

    def __init__(self, ops: Operators, K: np.ndarray, Phi_u: np.ndarray | None = None,
                 name: str = "controller"):
        size = (ops.m * (ops.T + 1), ops.n * (ops.T + 1))
        self.K = as_matrix(K, f"{name}: K", size)
        if not ops.is_causal(self.K, tol=0.0):
            raise ShapeError(f"{name}: K", "block lower-triangular (causal)", "non-causal entries",
                             what="structure")
        self.ops, self.Phi_u, self.name = ops, Phi_u, name
        self.reset()

    @classmethod
    def from_result(cls, result: object, allow_inaccurate: bool = False) -> RegretController:
        """The controller of a synthesis result
        (:class:`~balustrade.control.regret_synthesis.SynthesisResult`): its gain if the
        result is certified (``ok``), or, with
        ``allow_inaccurate``, if it ended ``optimal_inaccurate`` with a gain."""
        K = result.gain(allow_inaccurate)
        return cls(result.ops, K, result.Phi_u, name=result.name)

    def reset(self) -> None:
        """Forget the state history: the next :meth:`step` is time ``k = 0``."""
        self.k = 0
        self._hist = np.zeros((self.ops.T + 1, self.ops.n))
        self._u_prev = np.zeros(self.ops.m)

    def input(self, k: int, x_hist: np.ndarray) -> np.ndarray:
        """u_k = Σ_{j≤k} K_{k,j} x_j from the states x_0..x_k (rows of ``x_hist``)."""
        ops = self.ops
        rows = ops.u_blocks[k]
        cols = slice(0, ops.x_blocks[k].stop)
        return self.K[rows, cols] @ x_hist[: k + 1].reshape(-1)

    def step(self, x: np.ndarray, u_p: np.ndarray | None = None
             ) -> tuple[np.ndarray, StepInfo]:
        """``u_k`` of (3.15) for the measured ``x = x_k`` (``k`` counts the calls since
        :meth:`reset`). Past the horizon (``k > T``) there is no gain: the input is 0 and
        ``StepInfo`` says so (``"beyond_horizon"``, fallback ``"zero_input"``). A NaN/inf
        ``x`` is replaced by its nominal prediction (``"non_finite_state"``, fallback
        ``"nominal_prediction"``); a wrong size raises a ``BalustradeError``."""
        # wrong sizes or non-numbers are errors; NaN/inf states are handled below
        x = as_vector(x, f"{self.name}.step: x", self.ops.n, finite=False)
        if u_p is not None:  # not used by the law, but a wrong one is the caller's error
            as_vector(u_p, f"{self.name}.step: u_p", self.ops.m, finite=False)
        if self.k > self.ops.T:
            self.k += 1
            return np.zeros(self.ops.m), StepInfo(status="beyond_horizon",
                                                  fallback="zero_input")
        info = StepInfo()
        if not np.all(np.isfinite(x)):
            # a NaN state would enter every later input of the causal law (3.15); use the
            # nominal prediction x̂_k = A_{k−1} x_{k−1} + B_{k−1} u_{k−1} (w = 0; 0 at k = 0)
            x = self._predicted()
            info = StepInfo(status="non_finite_state", fallback="nominal_prediction")
        self._hist[self.k] = x
        u = self.input(self.k, self._hist)
        self._u_prev = u
        self.k += 1
        return u, info

    def _predicted(self) -> np.ndarray:
        """``A_{k−1} x_{k−1} + B_{k−1} u_{k−1}`` (the state with ``w_{k−1} = 0``); 0 at
        ``k = 0``."""
        if self.k == 0:
            return np.zeros(self.ops.n)
        sysm, k = self.ops.system, self.k
        return sysm.A[k - 1] @ self._hist[k - 1] + sysm.B[k - 1] @ self._u_prev

    def simulate(self, x0: object, w: object, constraints: object = None) -> Rollout:
        """:func:`rollout` of this controller from ``x0`` under the disturbances ``w``."""
        return rollout(self, x0, w, constraints)


def rollout(controller: RegretController, x0: object, w: object,
            constraints: object = None) -> Rollout:
    """Closed loop ``x_{k+1} = A_k x_k + B_k u_k + E_k w_k`` for ``k < T`` with
    ``u_k`` from ``controller.step`` (reset first), and ``u_T`` (cost only).

    ``constraints`` (a :class:`~balustrade.problems.regret.synthesis.StateInputConstraints`)
    gives :attr:`Rollout.violation`."""
    if not isinstance(controller, RegretController):
        raise BalustradeError(f"rollout: expected a RegretController, got "
                              f"{type(controller).__name__}")
    ops, sysm = controller.ops, controller.ops.system
    T, n = ops.T, ops.n
    x0v = as_vector(x0, "rollout: x0", n)
    wm = np.asarray(w, dtype=float).reshape(T, -1) if np.size(w) == T * ops.p else None
    if wm is None:
        raise ShapeError("rollout: w", (T, ops.p), np.shape(w))
    controller.reset()
    x = np.zeros((T + 1, n))
    u = np.zeros((T + 1, ops.m))
    x[0] = x0v
    infos, times, no_proposal = [], np.zeros(T + 1), np.zeros(ops.m)
    for k in range(T + 1):
        start = time.perf_counter()
        u[k], info = controller.step(x[k], no_proposal)
        times[k] = time.perf_counter() - start
        infos.append(info)
        if k < T:
            x[k + 1] = sysm.A[k] @ x[k] + sysm.B[k] @ u[k] + sysm.E[k] @ wm[k]
    trace = Trace(x, u, np.zeros_like(u), wm, {}, [i.status for i in infos],
                  [i.fallback for i in infos], np.zeros(T + 1), times,
                  uncertified=[{} for _ in infos])
    J = ops.cost(x.reshape(-1), u.reshape(-1))
    J_star = ops.noncausal_cost(ops.delta(x0v, wm))
    viol = None if constraints is None else constraints.violation(x, u)
    return Rollout(trace, J, J_star, viol)


__all__ = ["RegretController", "Rollout", "rollout"]
