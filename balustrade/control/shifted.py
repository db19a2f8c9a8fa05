"""The shifted plan as a certificate of ``h_PB = 0`` (thesis Section 2.4, the
recursive-feasibility argument behind Theorem 2.30, SPEC §2.7).

If the plan applied at step ``k`` was computed with ``ξ* = 0`` (``x_k ∈ S_PB``), its shift by
one step — inputs ``u_{1|k} … u_{N−1|k}`` and a tail input ``0``, rolled out from the
measured ``x_{k+1}`` with the model — meets the constraints of the slack problem (2.24) at
``x_{k+1}`` with zero slacks: the growth ``Δ_{j+1} − Δ_j`` of the tightening absorbs the
filter's ``eps``, and the terminal constraint holds again when the terminal set is invariant
under the zero input (e.g. the stop ``v_N = 0`` of Section 8.3, SPEC §2.32). Its cost, 0, is
the lower bound ``h_PB >= 0``: the candidate is a *global* minimizer of (2.24).

On a nonconvex (2.24) (disc obstacles) a local NLP solver can converge to a KKT point with
a positive cost although such a candidate exists, even when started from it (measured on the
obstacle car, docs/obstacles.md: the interior-point solver returned ``optimal`` with
``h_PB = 0.031`` where the shifted plan had zero slack). The filter (2.23) then relaxes
the constraints by that spurious ``ξ*`` and the car enters an obstacle: the theorem's
assumption that (2.24) is solved to its optimum is what fails. :class:`ShiftedCertificate`
checks the candidate exactly (every declared block and bound of the OCP, the declared cost)
so that the PCBF filter uses it in place of such a local optimum.

A candidate that does not meet every row within :data:`FEASIBILITY_TOL` or whose cost
exceeds the zero tolerance certifies nothing (``None``), e.g. after a step with ``ξ* > 0`` or
for a terminal set that the zero input does not keep invariant.
"""

from __future__ import annotations

import time

import casadi as ca
import numpy as np

from balustrade.backends import Compiled, Solution
from balustrade.backends.solution import FEASIBILITY_TOL
from balustrade.errors import BalustradeError


class ShiftedCertificate:
    """Evaluate the shifted plan as a point of a compiled slack problem (2.24).

    ``compiled`` must carry its :class:`~balustrade.dsl.ocp.OCP` (``compiled.ocp``) with a
    system and the initial-state parameter ``x0``; otherwise :attr:`available` is ``False``
    and :meth:`check` returns ``None``. Variables other than the state and input
    trajectories (slacks, epigraph variables) are set to 0 in the candidate.
    """

    def __init__(self, compiled: Compiled, zero_tol: float, tol: float = FEASIBILITY_TOL):
        ocp = getattr(compiled, "ocp", None)
        self.ocp, self.zero_tol, self.tol = ocp, float(zero_tol), float(tol)
        self.backend = str(getattr(compiled, "backend", "casadi"))
        self.available = bool(ocp is not None and ocp.system is not None
                              and "x0" in ocp.parameters and ocp.system.ntheta == 0)
        self._evaluate: ca.Function | None = None
        self._roll: ca.Function | None = None
        self._certify: ca.Function | None = None

    def _function(self) -> ca.Function:
        """``(w, p) → (inequality rows, equality rows, cost)`` of the declared OCP."""
        if self._evaluate is None:
            ocp = self.ocp
            le = [b.expr for b in ocp.blocks if b.kind == "le"]
            eq = [b.expr for b in ocp.blocks if b.kind == "eq"]
            self._evaluate = ca.Function(
                "shifted_certificate", [ocp.decision_vector(), ocp.parameter_vector()],
                [ca.vertcat(ca.SX(0, 1), *le), ca.vertcat(ca.SX(0, 1), *eq),
                 ocp.cost.expr()])
        return self._evaluate

    def _rollout(self) -> ca.Function:
        """``(x, U) → [x, f(x, u_0), …]`` (``(nx, N+1)``) with the model, ``w = 0``."""
        if self._roll is None:
            system, N = self.ocp.system, self.ocp.N
            x0, U = ca.SX.sym("x0", system.nx), ca.SX.sym("U", system.nu, N)
            xs = [x0]
            for j in range(N):
                xs.append(system(xs[-1], U[:, j]))
            self._roll = ca.Function("shifted_rollout", [x0, U], [ca.horzcat(*xs)])
        return self._roll

    def function(self, name: str = "shift_cert") -> ca.Function:
        """``(x, U) → (w, violation, cost)``: the candidate (decision vector ``w`` of the
        declared OCP: the roll-out of ``U`` (``(nu, N)``) from ``x`` as the states, ``U`` as
        the inputs, every other variable 0), its largest violation of a declared block or
        bound (``max(le, |eq|, lb − w, w − ub)``) and its declared cost, with the parameter
        ``x0 = x`` (others at their declared values). :meth:`check` decides with it and the
        emitted C (:func:`balustrade.codegen.emit_pcbf`) evaluates the same function, so the
        certificate has one definition. Requires :attr:`available`."""
        if self._certify is not None and self._certify.name() == name:
            return self._certify
        if not self.available:
            raise BalustradeError("ShiftedCertificate.function: the certificate needs an OCP "
                                  "with a system, the parameter x0 and no theta")
        ocp = self.ocp
        system, N = ocp.system, ocp.N
        x, U = ca.SX.sym("x", system.nx), ca.SX.sym("U", system.nu, N)
        X = self._rollout()(x, U)
        blocks = {ocp.state_name: X, ocp.input_name: U}
        w = ca.vertcat(ca.SX(0, 1), *[
            ca.vec(blocks[e.name]) if e.name in blocks else ca.SX.zeros(e.size, 1)
            for e in ocp.variable_layout.entries])
        chunks = []
        for e in ocp.parameter_layout.entries:
            if e.name == "x0":
                chunks.append(x)
            elif e.init is not None:
                chunks.append(ca.SX(ca.DM(np.asarray(e.init, float).reshape(-1))))
            else:
                raise BalustradeError(f"ShiftedCertificate.function: parameter {e.name!r} "
                                      "has no declared value")
        p = ca.vertcat(ca.SX(0, 1), *chunks)
        le, eq, cost = self._function()(w, p)
        lb, ub = ocp.bounds()
        rows = [le, ca.fabs(eq)]
        lo, hi = np.isfinite(lb), np.isfinite(ub)
        if lo.any():
            rows.append(ca.DM(lb[lo]) - w[np.flatnonzero(lo).tolist()])
        if hi.any():
            rows.append(w[np.flatnonzero(hi).tolist()] - ca.DM(ub[hi]))
        rows = ca.vertcat(ca.SX(-np.inf), *rows)
        self._certify = ca.Function(name, [x, U], [w, ca.mmax(rows), cost],
                                    ["x", "U"], ["w", "violation", "cost"])
        return self._certify

    def padded(self, inputs: np.ndarray) -> np.ndarray:
        """``inputs`` (``(nu, m)``) padded with zeros (or cut) to ``(nu, N)``."""
        U = np.zeros((self.ocp.system.nu, self.ocp.N))
        m = min(self.ocp.N, inputs.shape[1])
        U[:, :m] = inputs[:, :m]
        return U

    def check(self, x: np.ndarray, inputs: np.ndarray | None) -> Solution | None:
        """The shifted plan as an ``optimal`` :class:`Solution` of (2.24) at ``x`` if it
        meets every declared block and bound within ``tol`` with cost ``<= zero_tol``
        (then ``h_PB(x) = 0`` exactly, by the lower bound); else ``None``."""
        if not self.available or inputs is None or not np.all(np.isfinite(x)):
            return None
        start = time.perf_counter()
        try:
            p = self.ocp.pack_parameters({"x0": x})
            w, violation, cost = (np.asarray(v, float).reshape(-1) for v in self.function().call(
                [np.asarray(x, float), self.padded(np.asarray(inputs, float))]))
        except BalustradeError:  # parameters without a value
            return None
        violation, cost = float(violation[0]), float(cost[0])
        # a non-finite roll-out certifies nothing (NaN compares false everywhere)
        if not (np.all(np.isfinite(w)) and np.isfinite(violation) and np.isfinite(cost)):
            return None
        if not (violation <= self.tol and abs(cost) <= self.zero_tol):
            return None
        return Solution(status="optimal", objective=max(cost, 0.0),
                        primal=self.ocp.unpack_variables(w), dual={},
                        solve_time=time.perf_counter() - start, iterations=0,
                        backend=self.backend, solver="shifted_plan", p=p,
                        message="shifted plan: feasible with zero slack, h_PB = 0 "
                                "(lower bound)")


__all__ = ["ShiftedCertificate"]
