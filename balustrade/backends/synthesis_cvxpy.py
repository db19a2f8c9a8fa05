"""Lower a :class:`~balustrade.dsl.synthesis.SynthesisProblem` to cvxpy, once; solve many times.

The expression tree of the language maps node by node onto cvxpy atoms (variables →
``cp.Variable`` with their symmetric/PSD/nonneg attributes, parameters → ``cp.Parameter`` so
re-solves with new data reuse cvxpy's DPP canonicalization, ``bmat`` → ``cp.bmat``,
``logdet`` → ``cp.log_det``, ``norm`` → ``cp.norm``, LMIs → ``>>``). The problem is built
in :class:`CompiledSynthesis`'s constructor; :meth:`CompiledSynthesis.solve` only sets
parameter values and calls the solver of the target (default preset ``"sdp"``: Clarabel).
Every outcome is a :class:`~balustrade.backends.synthesis_solution.SynthesisSolution` with a
status of the common vocabulary; solver exceptions and refusals (a PSD cone too large for
the available memory) are statuses with a message, never exceptions.
"""

from __future__ import annotations

import time
from collections.abc import Mapping

import cvxpy as cp
import numpy as np

from balustrade.backends.cvxpy_backend import solve_cvxpy
from balustrade.backends.synthesis_solution import SynthesisSolution
from balustrade.backends.targets import Target
from balustrade.backends.targets import target as resolve_target
from balustrade.dsl.synthesis import (
    Expr,
    SynthesisProblem,
    add_terms,
    check_parameter_value,
)
from balustrade.errors import BalustradeError, SolverError

#: the solver used when a cvxpy target names none (every SDP of balustrade is solved with it)
DEFAULT_SDP_SOLVER = "CLARABEL"

#: Clarabel keeps a dense block of (svec size)² per PSD cone in its KKT system; the measured
#: peak resident memory was ≈ 7 such blocks of 8-byte floats (22.8 GB for the 203-cone of the
#: regret SDP SCRW at T = 25)
CLARABEL_DENSE_CONE_BYTES = 7 * 8
#: share of the available memory a solve may plan to use before it is refused
MEMORY_SHARE = 0.8

#: cvxpy statuses → synthesis statuses
_STATUS = {
    cp.OPTIMAL: "optimal",
    cp.OPTIMAL_INACCURATE: "optimal_inaccurate",
    cp.INFEASIBLE: "infeasible",
    cp.INFEASIBLE_INACCURATE: "failed",
    cp.UNBOUNDED: "unbounded",
    cp.UNBOUNDED_INACCURATE: "failed",
    cp.USER_LIMIT: "max_iterations",
    cp.SOLVER_ERROR: "failed",
}


class CompiledSynthesis:
    """A synthesis problem lowered to cvxpy for one target; :meth:`solve` it many times."""

    backend = "cvxpy"

    def __init__(self, problem: SynthesisProblem, target: Target):
        if not isinstance(problem, SynthesisProblem):
            raise BalustradeError(f"compile_synthesis: expected a SynthesisProblem, got "
                                  f"{type(problem).__name__}")
        if target.backend != "cvxpy":
            raise SolverError(f"compile_synthesis({problem.name}): synthesis problems lower to "
                              f"cvxpy; target {target.name!r} uses {target.backend}")
        installed = cp.installed_solvers()
        self.solver = (target.solver or DEFAULT_SDP_SOLVER).upper()
        if self.solver not in installed:
            raise SolverError(f"compile_synthesis({problem.name}): unknown or uninstalled "
                              f"cvxpy solver {target.solver!r}; installed: "
                              f"{', '.join(installed)}")
        if not problem.variables:
            raise BalustradeError(f"compile_synthesis: {problem.name} has no variables")
        self.problem, self.target = problem, target
        self.options = target.solver_options()
        self.variables = {n: _variable(d) for n, d in problem.variables.items()}
        self.parameters = {n: _parameter(d) for n, d in problem.parameters.items()}
        self._memo: dict[int, object] = {}
        self.constraints: dict[str, cp.Constraint] = {
            name: self._constraint(name, c) for name, c in problem.constraints.items()}
        if problem.objective is None:
            objective = cp.Minimize(0)
        else:
            expr = self.lower(problem.objective)
            if problem.objective.shape:
                expr = cp.reshape(expr, (), order="F")
            objective = cp.Minimize(expr) if problem.sense == "minimize" else cp.Maximize(expr)
        self.cvxpy_problem = cp.Problem(objective, list(self.constraints.values()))
        self.psd_sizes = psd_cone_sizes(self.cvxpy_problem, problem)

    # -- lowering ---------------------------------------------------------------------------
    def lower(self, e: Expr) -> object:
        """The cvxpy expression (or numpy constant) of ``e``."""
        key = id(e)
        if key not in self._memo:
            self._memo[key] = self._lower(e)
        return self._memo[key]

    def _lower(self, e: Expr) -> object:
        op, args = e.op, e.args
        if op == "variable":
            return self.variables[e.data.name]
        if op == "parameter":
            return self.parameters[e.data.name]
        if op == "constant":
            return float(e.data) if e.data.ndim == 0 else e.data
        if op == "bmat":
            return cp.bmat([[self.lower(b) for b in row] for row in args])
        if op == "add":  # left to right, without recursing down long sums
            terms = add_terms(e)
            out = self.lower(terms[0])
            for t in terms[1:]:
                out = out + self.lower(t)
            return out
        sub = [self.lower(a) for a in args]
        if op == "neg":
            return -sub[0]
        if op == "mul":
            return sub[0] * sub[1]
        if op == "div":
            return sub[0] / sub[1]
        if op == "matmul":
            return sub[0] @ sub[1]
        if op == "transpose":
            return sub[0].T
        if op == "index":
            return sub[0][e.data]
        if op == "reshape":
            return cp.reshape(sub[0], e.data, order="F")
        if op == "trace":
            return cp.trace(sub[0])
        if op == "sum":
            return cp.sum(sub[0])
        if op == "hstack":
            return cp.hstack(sub)
        if op == "vstack":
            return cp.vstack(sub)
        if op == "diag":
            return cp.diag(sub[0])
        if op == "multiply":
            return cp.multiply(sub[0], sub[1])
        if op == "sum_squares":
            return cp.sum_squares(sub[0])
        if op == "norm":
            return cp.norm(sub[0], e.data)
        if op == "logdet":
            return cp.log_det(sub[0])
        raise BalustradeError(f"compile_synthesis: no cvxpy lowering for {op!r}")

    def _constraint(self, name: str, c) -> cp.Constraint:
        lhs, rhs = self.lower(c.lhs), self.lower(c.rhs)
        try:
            if c.kind == "==":
                return lhs == rhs
            if c.kind == "<=":
                return lhs <= rhs
            if c.kind == "soc":
                return cp.SOC(cp.reshape(rhs, (c.lhs.shape[1 - c.axis],), order="F"), lhs,
                              axis=c.axis)
            return lhs >> rhs
        except (ValueError, cp.error.DCPError) as exc:
            raise BalustradeError(f"compile_synthesis({self.problem.name}): constraint "
                                  f"{name!r}: {exc}") from exc

    # -- solving ------------------------------------------------------------------------------
    def solve(self, params: Mapping[str, object] | None = None) -> SynthesisSolution:
        """Set the parameters (``params`` by name; declared defaults otherwise) and solve."""
        params = dict(params or {})
        unknown = set(params) - set(self.parameters)
        if unknown:
            raise BalustradeError(f"{self.problem.name}: unknown parameters "
                                  f"{sorted(unknown)}; declared: {sorted(self.parameters)}")
        for name, decl in self.problem.parameters.items():
            value = params.get(name, decl.value)
            if value is None:
                raise BalustradeError(f"{self.problem.name}: parameter {name!r} has no value "
                                      "(give it to solve() or declare a default)")
            self.parameters[name].value = check_parameter_value(decl, value, self.problem.name)
        refusal = self._memory_refusal()
        if refusal:
            return SynthesisSolution("failed", refusal, target=self.target,
                                     info={"psd_cone_sizes": self.psd_sizes})
        prob = self.cvxpy_problem
        start = time.perf_counter()
        cvx_status, message = solve_cvxpy(prob, self.solver, self.options)
        elapsed = time.perf_counter() - start
        status = _STATUS.get(cvx_status, "failed")
        stats = getattr(prob, "solver_stats", None)
        solver_time = float(stats.solve_time) if stats is not None and stats.solve_time \
            else float("nan")
        sol = SynthesisSolution(status, message, solve_time=elapsed, solver_time=solver_time,
                                target=self.target,
                                info={"psd_cone_sizes": self.psd_sizes,
                                      "iterations": getattr(stats, "num_iters", None)})
        if sol.ok:
            sol.objective = float(prob.value)
            sol.values = {n: np.array(v.value, dtype=float).reshape(v.shape)
                          for n, v in self.variables.items() if v.value is not None}
            sol.duals = {n: _dual(c.dual_value) for n, c in self.constraints.items()
                         if c.dual_value is not None}
            if len(sol.values) != len(self.variables):
                sol.status = "failed"
                sol.message += "; the solver returned no value for some variables"
        return sol

    def _memory_refusal(self) -> str:
        """Why the solve is refused for memory (Clarabel's dense PSD cones), or ``""``."""
        if self.solver != "CLARABEL" or not self.psd_sizes:
            return ""
        return dense_cone_refusal(self.problem.name, self.psd_sizes[0])


def psd_cone_sizes(cvxpy_problem: cp.Problem, problem: SynthesisProblem) -> list[int]:
    """The sizes of the PSD cones of ``cvxpy_problem`` and of the PSD variables of
    ``problem``, largest first."""
    return sorted({int(c.args[0].shape[0]) for c in cvxpy_problem.constraints
                   if isinstance(c, cp.PSD)}
                  | {d.shape[0] for d in problem.variables.values() if d.psd}, reverse=True)


def dense_cone_refusal(name: str, size: int) -> str:
    """Why a solve of problem ``name`` with a dense PSD cone of ``size`` is refused for
    memory under Clarabel, or ``""`` when it fits."""
    svec = size * (size + 1) // 2
    need = CLARABEL_DENSE_CONE_BYTES * float(svec) ** 2
    avail = _mem_available_bytes()
    if need <= MEMORY_SHARE * avail:
        return ""
    return (f"too large: {name}: one dense PSD cone of size {size} needs about "
            f"{need / 2**30:.1f} GB with Clarabel, {avail / 2**30:.1f} GB available; use "
            "a target with solver 'scs' (it only needs eigendecompositions of the cone)")


def _dual(value: object) -> np.ndarray | list[np.ndarray]:
    """A multiplier as an array (a list of arrays for a cone with several parts, e.g. SOC)."""
    if isinstance(value, list | tuple):
        return [np.array(v, dtype=float) for v in value]
    return np.array(value, dtype=float)


def _variable(d) -> cp.Variable:
    kwargs = {"PSD": True} if d.psd else {"symmetric": True} if d.symmetric else {}
    if d.nonneg:
        kwargs["nonneg"] = True
    return cp.Variable(d.shape, name=d.name, **kwargs)


def _parameter(d) -> cp.Parameter:
    kwargs = {"PSD": True} if d.psd else {"symmetric": True} if d.symmetric else {}
    if d.nonneg:
        kwargs["nonneg"] = True
    return cp.Parameter(d.shape, name=d.name, **kwargs)


def _mem_available_bytes() -> float:
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable"):
                    return int(line.split()[1]) * 1024.0
    except OSError:
        pass
    return float("inf")


def compile_synthesis(problem: SynthesisProblem, target: Target | str | None = "sdp", *,
                      solver: str | None = None, options: dict | None = None
                      ) -> CompiledSynthesis:
    """Lower ``problem`` once for ``target`` (a :class:`Target`, a preset name — ``"sdp"``
    by default — or ``"cvxpy"``); ``solver``/``options`` override the target's. Only the
    target's own options reach the solver (no backend defaults are added: ``"conic"``
    and ``"sdp"`` both run Clarabel with its own tolerances here)."""
    try:
        tgt = resolve_target(target, default="sdp", solver=solver, options=options)
    except SolverError as exc:
        raise SolverError(f"{getattr(problem, 'name', 'synthesis')}: {exc}") from None
    return CompiledSynthesis(problem, tgt)


def solve_synthesis(problem: SynthesisProblem, target: Target | str | None = "sdp",
                    params: Mapping[str, object] | None = None, *, solver: str | None = None,
                    options: dict | None = None) -> SynthesisSolution:
    """Compile and solve once (see :func:`compile_synthesis`)."""
    return compile_synthesis(problem, target, solver=solver, options=options).solve(params)


__all__ = ["CLARABEL_DENSE_CONE_BYTES", "DEFAULT_SDP_SOLVER", "CompiledSynthesis",
           "compile_synthesis", "solve_synthesis"]
