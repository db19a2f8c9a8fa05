"""Lowering of an :class:`~balustrade.dsl.ocp.OCP` to a DPP-parametrized cvxpy problem.

The lowering is the chain :data:`balustrade.backends.passes.CVXPY_CHAIN`: (1) classify
every block row as affine, convex quadratic jointly in the decision variables and parameters
(kept about its centre as a cone, e.g. the tube row (5.15b)), or convex quadratic in the
decision variables (:mod:`~balustrade.backends.passes.classify`), refusing anything else
with an error naming the block; (2) build one decision vector ``W`` and one parameter vector
``P`` and the cvxpy atoms, leaving out bounds and rows whose bound is "infinite" (``|b| >=
INFINITE_BOUND``) (:mod:`~balustrade.backends.passes.to_cvxpy`). This module then picks the
solver (PIQP for LPs/QPs, Clarabel for SOCPs) unless one is given, and solves.

The compiled problem is re-solved with new parameter values without rebuilding (cvxpy's DPP
canonicalization is cached), and each solve is independent of the earlier ones: cvxpy's
``warm_start=True`` would re-use the solver object of the previous solve (Clarabel's and
PIQP's equilibration of the *previous* data, OSQP's/SCS's previous iterate), so it is only
passed when the caller asks for a warm start that the solver can actually use
(:meth:`CvxpyCompiled.solve`).
"""

from __future__ import annotations

import time
import warnings

import cvxpy as cp
import numpy as np

from balustrade.backends.passes import CVXPY_CHAIN, run_chain
from balustrade.backends.passes.to_cvxpy import (  # noqa: F401 - re-exported limits
    INFINITE_BOUND,
    LARGE_BOUND,
    CvxpyProgram,
)
from balustrade.backends.solution import Solution, Status
from balustrade.dsl.ocp import OCP
from balustrade.errors import BalustradeError, SolverError

#: a cost coefficient above this makes a failed solve be retried with the cost rescaled
BIG_WEIGHT = 1e6

#: solvers whose cvxpy interface warm-starts from the variables' values (``W.value``)
_WARM_FROM_VALUES = frozenset({"GUROBI", "MOSEK", "CPLEX", "XPRESS", "COPT"})
#: solvers whose cvxpy interface warm-starts from its cached previous solution
_WARM_FROM_CACHE = frozenset({"OSQP", "SCS"})

SOLVER_OPTIONS: dict[str, dict] = {
    "PIQP": {"eps_abs": 1e-10, "eps_rel": 1e-11, "max_iter": 500},
    "CLARABEL": {"tol_gap_abs": 1e-10, "tol_gap_rel": 1e-10, "tol_feas": 1e-10,
                 "tol_ktratio": 1e-8, "max_iter": 300},
    "SCS": {"eps_abs": 1e-9, "eps_rel": 1e-9, "max_iters": 100000},
    "OSQP": {"eps_abs": 1e-9, "eps_rel": 1e-9, "max_iter": 100000, "polishing": True},
}


class CvxpyCompiled:
    """A compiled cvxpy problem: call :meth:`solve` with parameter values."""

    backend = "cvxpy"

    def __init__(self, ocp: OCP, solver: str | None = None, options: dict | None = None):
        self.ocp = ocp
        program, _ = run_chain(CVXPY_CHAIN, ocp)
        self.program: CvxpyProgram = program
        self.W, self.P, self.problem = program.W, program.P, program.problem
        self.conic, self.derived, self.large = program.conic, program.derived, program.large
        self.block_constraints = program.block_constraints
        self.bound_constraints = program.bound_constraints
        self.cost_scale = program.cost_scale
        self._objective = program.objective
        self._full: cp.Problem | None = None  # with the large rows, built when needed
        self.solver_name = self._choose_solver(solver)
        self.solver_options = {**SOLVER_OPTIONS.get(self.solver_name, {}), **(options or {})}
        #: the direct lowering that checks "infeasible" (built on the first such verdict;
        #: a str: why this OCP has none)
        self._infeasibility: object | str | None = None
        self._scaled: cp.Problem | None = None  # built on the first failure, see _rescaled
        self._last: Solution | None = None  # what the solver cache of OSQP/SCS holds

    # -- solver choice (PIQP for LPs/QPs, Clarabel for SOCPs) ----------------------------
    def _choose_solver(self, solver: str | None) -> str:
        installed = cp.installed_solvers()
        if solver is None:
            return "CLARABEL" if self.conic else ("PIQP" if "PIQP" in installed else "CLARABEL")
        name = solver.upper()
        if name not in installed:
            raise SolverError(f"{self.ocp.name}: unknown or uninstalled cvxpy solver "
                              f"{solver!r}; installed: {', '.join(installed)}")
        return name

    # -- solve -----------------------------------------------------------------------
    def solve(self, params: dict[str, object] | None = None,
              warm_start: Solution | dict[str, object] | None = None) -> Solution:
        """Solve with the given parameter values.

        Without ``warm_start`` the answer depends on ``params`` only (no solver state is
        carried over from earlier solves). ``warm_start`` (a previous :class:`Solution` or a
        dict of variable values) is used where the solver can start from it: solvers that
        read the variables' values (Gurobi, MOSEK, ...) get it as ``W.value``; OSQP and SCS
        start from their cached last solution, so only when ``warm_start`` is the last
        solution this object returned; the interior-point solvers PIQP and Clarabel have no
        warm start through cvxpy and always start from scratch.
        """
        p = self.ocp.pack_parameters(params)
        if self.P is not None:
            self.P.value = p
        for phi, param in self.derived:
            param.value = float(phi(p))
        warm = self._use_warm_start(warm_start)
        start = time.perf_counter()
        status, message = _run(self.problem, self.solver_name, self.solver_options, warm)
        first_message = message
        if status == Status.INFEASIBLE:
            status, message = self._check_infeasible(message, p)
        if self.large is not None and not (status == Status.INFEASIBLE or self._within_large()):
            first = "violated them" if status.success else status
            status, message = _run(self._full_problem(), self.solver_name,
                                   self.solver_options, False)
            message += (f" (with the {self.large.c.size} large bounds/rows |b| >= "
                        f"{LARGE_BOUND:g}; the solve without them: {first})")
            if status == Status.INFEASIBLE:         # the full problem's verdict needs evidence
                status, message = self._check_infeasible(message, p, full=True)
        if status in (Status.FAILED, Status.MAX_ITERATIONS, Status.OPTIMAL_INACCURATE) \
                and self.cost_scale > BIG_WEIGHT:
            status, message = self._rescaled(status, message)
        elapsed = time.perf_counter() - start
        n = self.W.size
        w = np.asarray(self.W.value, dtype=float).reshape(-1) if self.W.value is not None \
            and status not in (Status.INFEASIBLE, Status.FAILED, Status.MAX_ITERATIONS) \
            else np.full(n, np.nan)
        stats = self.problem.solver_stats
        dual = self._duals() if status in (Status.OPTIMAL, Status.OPTIMAL_INACCURATE) else {}
        objective = float(self._objective(w, p)) if np.all(np.isfinite(w)) else np.nan
        sol = Solution(status=status, objective=objective,
                       primal=self.ocp.unpack_variables(w), dual=dual,
                       solve_time=elapsed,
                       iterations=int(getattr(stats, "num_iters", 0) or 0) if stats else 0,
                       backend="cvxpy", solver=self.solver_name, p=p,  # w is derived from primal
                       message=message)
        # OSQP/SCS cache the last solve of self.problem: a warm start only if that is `sol`
        self._last = sol if message == first_message else None
        return sol

    def _use_warm_start(self, warm_start: Solution | dict | None) -> bool:
        """Whether cvxpy's ``warm_start=True`` passes the caller's point to the solver."""
        if warm_start is None:
            return False
        if self.solver_name in _WARM_FROM_CACHE:
            return warm_start is self._last and self._last.success
        if self.solver_name not in _WARM_FROM_VALUES:
            return False
        w = warm_start.w if isinstance(warm_start, Solution) else \
            self.ocp.pack_variables(dict(warm_start))
        if w.size != self.W.size or not np.all(np.isfinite(w)):
            return False
        self.W.value = w
        return True

    def _check_infeasible(self, message: str, p: np.ndarray,
                          full: bool = False) -> tuple[Status, str]:
        """An "infeasible" verdict stands only on evidence beyond the word of the solver that
        gave it (a badly scaled cost weight, a tolerance or a bug can make a solver declare
        a feasible problem infeasible, and asking it again can repeat the mistake): the same
        constraints, lowered once by the direct chain, are checked by
        :meth:`DirectCompiled.confirm_infeasible
        <balustrade.backends.direct_backend.DirectCompiled.confirm_infeasible>` — a
        feasibility solve whose Farkas certificate passes
        :func:`~balustrade.backends.farkas.check_farkas`, or for an LP/QP the "infeasible" of
        an engine other than this solver; a feasible point overturns the verdict. Anything
        else (also an OCP the direct chain cannot lower) is ``failed`` with the reason.
        ``full``: the verdict is about the problem with its large bounds/rows."""
        checker = self._infeasibility_checker()
        if isinstance(checker, str):
            return Status.FAILED, (f"{message}; infeasibility not established: no independent "
                                   f"check ({checker})")
        confirmed, words = checker.confirm_infeasible(p, self.solver_name.lower(), message,
                                                      full=full)
        return (Status.INFEASIBLE if confirmed else Status.FAILED), words

    def _infeasibility_checker(self) -> object | str:
        """The :class:`~balustrade.backends.direct_backend.DirectCompiled` of this OCP that
        checks "infeasible" verdicts (built once; its engine for LPs/QPs is this solver when
        the direct backend has it, so that its checker is the *other* engine), or why there
        is none."""
        if self._infeasibility is None:
            # imported here: the direct backend imports this module (BIG_WEIGHT, LARGE_BOUND)
            from balustrade.backends.direct_backend import DirectCompiled
            from balustrade.backends.direct_engines import DIRECT_SOLVERS

            own = self.solver_name.lower()
            solver = own if own in DIRECT_SOLVERS and not self.conic else None
            try:
                self._infeasibility = DirectCompiled(self.ocp, solver)
            except BalustradeError as exc:
                self._infeasibility = f"the direct lowering refuses this OCP: {exc}"
        return self._infeasibility

    def _within_large(self) -> bool:
        """The solution exists and satisfies the large rows left out of the problem."""
        if self.problem.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) \
                or self.W.value is None:
            return False
        residual = self.large.A @ np.asarray(self.W.value).reshape(-1) + self.large.c
        return bool(np.all(residual <= 1e-12 * np.abs(self.large.c)))

    def _full_problem(self) -> cp.Problem:
        if self._full is None:
            self._full = cp.Problem(self.problem.objective, self.problem.constraints
                                    + [self.program.affine_expr(self.large) <= 0])
        return self._full

    def _rescaled(self, status: Status, message: str) -> tuple[Status, str]:
        """Re-solve with the cost divided by :attr:`cost_scale`: with weights of 1e9 and
        more (exact-penalty slacks) the multipliers are huge and PIQP/Clarabel mistake them
        for an infeasibility certificate or stall. The minimizer of the scaled problem is
        the same, but it is accurate only relative to the largest weight, hence at best
        ``optimal_inaccurate``."""
        if self._scaled is None:
            self._scaled = cp.Problem(cp.Minimize(self.problem.objective.args[0]
                                                  / self.cost_scale),
                                      self.problem.constraints)
        first = self.W.value
        retry, words = _run(self._scaled, self.solver_name, self.solver_options, False)
        if status == Status.OPTIMAL_INACCURATE and retry != Status.OPTIMAL:
            self.W.value = first  # keep the first answer unless the retry converged
            return status, message
        if retry in (Status.OPTIMAL, Status.OPTIMAL_INACCURATE):
            return Status.OPTIMAL_INACCURATE, (f"{message}; solved with the cost scaled by "
                                          f"1/{self.cost_scale:.3g}: {words}")
        return status, f"{message}; with the cost scaled by 1/{self.cost_scale:.3g}: {words}"

    def _duals(self) -> dict[str, np.ndarray]:
        out = {}
        for block in self.ocp.blocks:
            values = np.zeros(block.rows)
            for rows, con, scale in self.block_constraints[block.name]:
                if con.dual_value is not None:
                    values[rows] = scale * np.asarray(con.dual_value, dtype=float).reshape(-1)
            out[block.name] = values
        return out


def solve_cvxpy(problem: cp.Problem, solver: str, options: dict, **solve_args: object
                ) -> tuple[str, str]:
    """Solve ``problem`` with ``solver``; ``(cvxpy status, message)``, the message being
    cvxpy's status, the solver's own words and the text of a solver exception (which becomes
    the status ``solver_error``, never an exception). Shared by the OCP and the synthesis
    lowerings, which map the status each to their own vocabulary."""
    try:
        with warnings.catch_warnings():  # "Solution may be inaccurate": the status says so
            warnings.simplefilter("ignore", UserWarning)
            problem.solve(solver=solver, **solve_args, **options)
        cvx_status, error = problem.status, ""
    except cp.error.SolverError as exc:
        cvx_status, error = cp.SOLVER_ERROR, str(exc)
    words = _solver_words(problem, solver)
    return cvx_status, (cvx_status + (f" ({words})" if words else "")
                        + (f": {error}" if error else ""))


def _run(problem: cp.Problem, solver: str, options: dict, warm_start: bool
         ) -> tuple[Status, str]:
    """Solve ``problem``; ``(status, message)`` with the status one of the six of
    :class:`Solution` and the message cvxpy's status and the solver's own words."""
    cvx_status, message = solve_cvxpy(problem, solver, options, warm_start=warm_start)
    status = _STATUS.get(cvx_status, Status.FAILED)
    if cvx_status == cp.INFEASIBLE_INACCURATE:
        message += "; infeasibility not certified"
    return status, message


def _solver_words(problem: cp.Problem, solver: str) -> str:
    """The solver's own status (``PIQP_MAX_ITER_REACHED``, Clarabel's
    ``InsufficientProgress``...) from cvxpy's solver cache, or ``""``."""
    cached = getattr(problem, "_solver_cache", {}).get(solver)
    try:
        if solver == "PIQP":
            return str(cached[2].info.status.name)
        if solver == "CLARABEL":
            return str(cached.get_info().status)
    except (AttributeError, IndexError, TypeError):
        pass
    return ""


#: cvxpy statuses → :class:`Solution` statuses. Not certified (``*_inaccurate``) infeasibility
#: and unboundedness (a safety-filter OCP is never unbounded when well posed) are "failed",
#: with cvxpy's and the solver's words in ``Solution.message``; iteration and time limits are
#: "max_iterations".
_STATUS = {
    cp.OPTIMAL: Status.OPTIMAL,
    cp.OPTIMAL_INACCURATE: Status.OPTIMAL_INACCURATE,
    cp.INFEASIBLE: Status.INFEASIBLE,
    cp.INFEASIBLE_INACCURATE: Status.FAILED,
    cp.UNBOUNDED: Status.FAILED,
    cp.UNBOUNDED_INACCURATE: Status.FAILED,
    cp.USER_LIMIT: Status.MAX_ITERATIONS,
    cp.SOLVER_ERROR: Status.FAILED,
}
