"""Checking compiled problems without trusting their solver (DESIGN.md principle 3).

* :func:`verify` evaluates every declared block of an :class:`~balustrade.dsl.ocp.OCP` at a
  :class:`~balustrade.backends.Solution`'s primal point: dynamics residual, constraint
  violation per block, variable bounds (slack signs) and the reported objective.
* :func:`compare_backends` compiles one formulation on both backends and compares optima.

Users call these in their own tests; so do ours.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from balustrade.backends import Solution, compile
from balustrade.dsl.ocp import OCP
from balustrade.errors import BalustradeError


@dataclass
class VerificationReport:
    """Per-block maximal violations at a solution (0 means satisfied exactly)."""

    problem: str
    block_violation: dict[str, float]
    bound_violation: dict[str, float]
    dynamics_residual: float
    objective_error: float
    tol: float
    notes: list[str] = field(default_factory=list)

    @property
    def max_violation(self) -> float:
        values = list(self.block_violation.values()) + list(self.bound_violation.values())
        return max(values, default=0.0)

    @property
    def ok(self) -> bool:
        return self.max_violation <= self.tol and self.objective_error <= self.tol * 10

    def __str__(self) -> str:
        worst = sorted({**self.block_violation, **{f"bound:{k}": v for k, v in
                                                     self.bound_violation.items()}}.items(),
                       key=lambda kv: -kv[1])[:5]
        return (f"verify({self.problem}): {'ok' if self.ok else 'FAILED'}; max violation "
                f"{self.max_violation:.3g} (tol {self.tol:g}), dynamics residual "
                f"{self.dynamics_residual:.3g}, objective error {self.objective_error:.3g}; "
                f"worst: {', '.join(f'{k}={v:.3g}' for k, v in worst)}")

    def raise_if_failed(self) -> None:
        if not self.ok:
            raise BalustradeError(str(self))


def verify(problem: OCP, solution: Solution, tol: float = 1e-6) -> VerificationReport:
    """Check ``solution`` against the declared model of ``problem`` (no solver involved).

    Equality blocks report ``max |g|``, inequality blocks ``max(g, 0)``, variables the
    distance outside their bounds (so a negative slack declared nonnegative shows up); the
    objective is recomputed from the declared cost and compared relatively.
    """
    w_sym, p_sym = problem.decision_vector(), problem.parameter_vector()
    if solution.w.size != w_sym.numel() or solution.p.size != p_sym.numel():
        raise BalustradeError(f"verify({problem.name}): the solution has {solution.w.size} "
                              f"variables and {solution.p.size} parameters, the problem "
                              f"{w_sym.numel()} and {p_sym.numel()}: not a solution of it")
    if not np.all(np.isfinite(solution.w)):
        inf = float("inf")
        return VerificationReport(problem.name, {b.name: inf for b in problem.blocks}, {},
                                  inf, inf, tol, [f"no primal point ({solution.status})"])
    evaluate = ca.Function("blocks", [w_sym, p_sym], [b.expr for b in problem.blocks]
                           + [problem.cost.expr()])
    values = evaluate(solution.w, solution.p)
    block_violation, dynamics = {}, 0.0
    for block, value in zip(problem.blocks, values[:-1]):
        g = np.asarray(value, dtype=float).reshape(-1)
        viol = float(np.max(np.abs(g))) if block.kind == "eq" else float(np.max(g, initial=0.0))
        block_violation[block.name] = max(viol, 0.0)
        if block.tag == "dynamics":
            dynamics = max(dynamics, viol)
    bound_violation = {}
    primal = problem.unpack_variables(solution.w)
    for name, v in problem.variables.items():
        val = np.asarray(primal[name], dtype=float).reshape(v.shape)
        below = np.max(v.lb - val, initial=0.0)
        above = np.max(val - v.ub, initial=0.0)
        bound_violation[name] = float(max(below, above, 0.0))
    objective = float(values[-1])
    obj_err = abs(objective - solution.objective) / max(1.0, abs(objective))
    return VerificationReport(problem.name, block_violation, bound_violation, dynamics,
                              obj_err, tol)


@dataclass
class BackendComparison:
    """Optima of one formulation on two backends."""

    objectives: dict[str, float]
    statuses: dict[str, str]
    solutions: dict[str, Solution]

    @property
    def abs_diff(self) -> float:
        a, b = self.objectives.values()
        return abs(a - b)

    @property
    def rel_diff(self) -> float:
        a, b = self.objectives.values()
        return abs(a - b) / max(abs(a), abs(b), 1e-300)

    def agree(self, rtol: float = 1e-5, atol: float = 1e-6) -> bool:
        return all(s in ("optimal", "optimal_inaccurate") for s in self.statuses.values()) \
            and (self.abs_diff <= atol or self.rel_diff <= rtol)


def compare_backends(problem: OCP, params: dict[str, object] | None = None,
                     backends: tuple[tuple[str, str | None], ...] = (("casadi", "sqpmethod"),
                                                                    ("cvxpy", None)),
                     compiled: dict | None = None) -> BackendComparison:
    """Compile ``problem`` on two backends (or reuse ``compiled``) and solve both."""
    compiled = compiled if compiled is not None else {
        f"{b}/{s or 'default'}": compile(problem, b, s) for b, s in backends}
    sols = {key: c.solve(params) for key, c in compiled.items()}
    return BackendComparison({k: s.objective for k, s in sols.items()},
                             {k: s.status for k, s in sols.items()}, sols)
