"""Checking compiled problems without trusting their solver (DESIGN.md principle 3).

* :func:`verify` evaluates every declared block of an :class:`~balustrade.dsl.ocp.OCP` at a
  :class:`~balustrade.backends.Solution`'s primal point (``sol.primal``, what the user sees,
  packed with the problem's own layout): dynamics residual, constraint violation per block,
  variable bounds (slack signs) and the reported objective. NaN is never "ok".
* :func:`compare_backends` compiles one formulation for two targets (e.g. both backends) and
  compares optima.

Users call these in their own tests; so do ours.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from balustrade._checks import as_float_array, as_scalar
from balustrade.backends import Solution, Target, compile, resolve_target
from balustrade.dsl.ocp import OCP
from balustrade.errors import BalustradeError, ShapeError


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
        """The largest violation; ``inf`` if any is NaN (a NaN is never satisfied)."""
        values = list(self.block_violation.values()) + list(self.bound_violation.values())
        return float(max((_nan_to_inf(v) for v in values), default=0.0))

    @property
    def ok(self) -> bool:
        return bool(self.max_violation <= self.tol
                    and _nan_to_inf(self.objective_error) <= self.tol * 10
                    and _nan_to_inf(self.dynamics_residual) <= self.tol)

    def __str__(self) -> str:
        worst = sorted({**self.block_violation, **{f"bound:{k}": v for k, v in
                                                     self.bound_violation.items()}}.items(),
                       key=lambda kv: -_nan_to_inf(kv[1]))[:5]
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
    objective is recomputed from the declared cost and compared relatively. The point is
    ``solution.primal`` (every declared variable, by name and shape); a NaN anywhere counts
    as an infinite violation.
    """
    if not isinstance(problem, OCP):
        raise BalustradeError(f"verify: expected an OCP as the problem, got "
                              f"{type(problem).__name__}")
    if not isinstance(solution, Solution):
        raise BalustradeError(f"verify({problem.name}): expected a Solution (from "
                              f"compile(...).solve), got {type(solution).__name__}")
    tol = as_scalar(tol, f"verify({problem.name}): tol", low=0.0)
    w_sym, p_sym = problem.decision_vector(), problem.parameter_vector()
    w = _pack_primal(problem, solution.primal)
    p = as_float_array(solution.p, f"verify({problem.name}): solution.p").reshape(-1)
    if p.size != p_sym.numel():
        raise BalustradeError(f"verify({problem.name}): the solution has {p.size} parameter "
                              f"values, the problem {p_sym.numel()}: not a solution of it")
    if not np.all(np.isfinite(p)):
        raise BalustradeError(f"verify({problem.name}): the solution's parameters contain "
                              "NaN or inf")
    if not np.all(np.isfinite(w)):
        inf = float("inf")
        return VerificationReport(problem.name, {b.name: inf for b in problem.blocks}, {},
                                  inf, inf, tol, [f"no primal point ({solution.status})"])
    evaluate = ca.Function("blocks", [w_sym, p_sym], [b.expr for b in problem.blocks]
                           + [problem.cost.expr()])
    values = evaluate.call([w, p])  # a list, also with a single output
    block_violation, dynamics = {}, 0.0
    for block, value in zip(problem.blocks, values[:-1]):
        g = np.asarray(value, dtype=float).reshape(-1)
        viol = _nan_to_inf(float(np.max(np.abs(g), initial=0.0)) if block.kind == "eq"
                           else float(np.max(g, initial=0.0)))
        block_violation[block.name] = max(viol, 0.0)
        if block.tag == "dynamics":
            dynamics = max(dynamics, viol)
    bound_violation = {}
    primal = problem.unpack_variables(w)
    for name, v in problem.variables.items():
        val = np.asarray(primal[name], dtype=float).reshape(v.shape)
        below = np.max(v.lb - val, initial=0.0)
        above = np.max(val - v.ub, initial=0.0)
        bound_violation[name] = float(max(below, above, 0.0))
    objective = float(values[-1])
    try:
        reported = float(solution.objective)
    except (TypeError, ValueError):
        reported = float("nan")
    obj_err = _nan_to_inf(abs(objective - reported) / max(1.0, abs(objective)))
    return VerificationReport(problem.name, block_violation, bound_violation, dynamics,
                              obj_err, tol)


def _nan_to_inf(value: float) -> float:
    return float("inf") if np.isnan(value) else float(value)


def _pack_primal(problem: OCP, primal: object) -> np.ndarray:
    """Stack ``primal`` with ``problem``'s layout; every declared variable must be there with
    its declared shape (a 1-D array for a column), and nothing else."""
    where = f"verify({problem.name})"
    if not isinstance(primal, dict):
        raise BalustradeError(f"{where}: solution.primal must be a dict, got "
                              f"{type(primal).__name__}")
    missing = [n for n in problem.variables if n not in primal]
    extra = [n for n in primal if n not in problem.variables]
    if missing or extra:
        raise BalustradeError(f"{where}: the solution's variables {list(primal)} are not the "
                              f"problem's {list(problem.variables)} (missing {missing}, "
                              f"unknown {extra}): not a solution of it")
    chunks = []
    for name, v in problem.variables.items():
        arr = as_float_array(primal[name], f"{where}: primal[{name!r}]")
        if arr.size != v.shape[0] * v.shape[1] or (arr.ndim == 2 and arr.shape != v.shape):
            raise ShapeError(f"{where}: primal[{name!r}]", v.shape, arr.shape)
        chunks.append(arr.reshape(v.shape, order="F" if arr.ndim < 2 else "C")
                      .reshape(-1, order="F"))
    return np.concatenate(chunks) if chunks else np.zeros(0)


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
                     targets: tuple[Target | str, ...] = ("fast-sqp", "cvxpy"),
                     compiled: dict | None = None) -> BackendComparison:
    """Compile ``problem`` for two targets (or presets, :mod:`balustrade.backends.targets`;
    or reuse ``compiled``, a dict label → compiled problem) and solve both; results are
    keyed by target name (``name#2`` for a second target of the same name, e.g. two
    unnamed :class:`~balustrade.backends.Target` objects, so neither hides the other)."""
    if compiled is None:
        compiled = {}
        for t in (resolve_target(t) for t in targets):
            key, k = t.name, 1
            while key in compiled:
                k += 1
                key = f"{t.name}#{k}"
            compiled[key] = compile(problem, t)
    sols = {key: c.solve(params) for key, c in compiled.items()}
    return BackendComparison({k: s.objective for k, s in sols.items()},
                             {k: s.status for k, s in sols.items()}, sols)
