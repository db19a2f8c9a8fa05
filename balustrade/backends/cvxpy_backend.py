"""Lowering of an :class:`~balustrade.dsl.ocp.OCP` to a DPP-parametrized cvxpy problem.

Passes: (1) classify every block row as affine, convex quadratic jointly in the decision
variables and parameters (kept about its centre as a cone, e.g. the tube row (5.15b)), or
convex quadratic in the decision variables (:mod:`balustrade.backends.structure`), refusing
anything else with an error naming the block; (2) build one decision vector ``W`` and one
parameter vector ``P`` and the cvxpy atoms, leaving out bounds and rows whose bound is
"infinite" (``|b| >= INFINITE_BOUND``); (3) pick the solver (PIQP for LPs/QPs, Clarabel for
SOCPs) unless one is given.

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

from balustrade.backends import structure
from balustrade.backends.solution import Solution
from balustrade.dsl.ocp import OCP
from balustrade.errors import ConvexityError, SolverError

#: bounds and constant row offsets at least this large in magnitude are infinite: such a
#: bound is not sent to the solver (an interior-point solver cannot hold a 1e30 row)
INFINITE_BOUND = 1e20
#: bounds (and constant row offsets) from this size on are "large but finite" (``|u| <= 1e12``
#: used as "unbounded"): they are left out of the problem sent first and only imposed, by a
#: second solve, when its solution violates them (a relaxation's minimizer that satisfies
#: the left-out rows is a minimizer of the whole problem); as rows they make PIQP and
#: Clarabel stall
LARGE_BOUND = 1e9

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
        w_sym, p_sym = ocp.decision_vector(), ocp.parameter_vector()
        self.W = cp.Variable(int(w_sym.numel()), name="w")
        self.P = cp.Parameter(int(p_sym.numel()), name="p") if p_sym.numel() else None
        self.conic = False  # becomes True when a second-order cone is needed
        self.derived: list[tuple] = []  # (CasADi function of p, cvxpy parameter)
        self._large_rows: list[structure.Affine] = []  # rows A w + c <= 0 with large |c|
        #: per block: (rows, constraint, factor from the constraint's dual to the rows')
        self.block_constraints: dict[str, list[tuple[np.ndarray, cp.Constraint, float]]] = {}
        constraints: list[cp.Constraint] = []
        for block in ocp.blocks:
            parts = self._lower_block(block, w_sym, p_sym)
            self.block_constraints[block.name] = parts
            constraints += [c for _, c, _ in parts]
        self.bound_constraints = self._bounds()
        objective = self._lower_cost(w_sym, p_sym)
        self.problem = cp.Problem(cp.Minimize(objective), constraints + self.bound_constraints)
        self.large = _stack(self._large_rows)
        self._full: cp.Problem | None = None  # with the large rows, built when needed
        if (self.P is not None or self.derived) and not self.problem.is_dpp():
            raise ConvexityError(f"{ocp.name}: parameters enter the problem in a way that is not "
                                 "DPP (disciplined parametrized); check parameter products")
        self.solver_name = self._choose_solver(solver)
        self.solver_options = {**SOLVER_OPTIONS.get(self.solver_name, {}), **(options or {})}
        self._feasibility: cp.Problem | None = None  # built on the first "infeasible"
        self._scaled: cp.Problem | None = None  # built on the first failure, see _rescaled
        self._last: Solution | None = None  # what the solver cache of OSQP/SCS holds
        import casadi as ca

        self._objective = ca.Function("objective", [w_sym, p_sym], [ocp.cost.expr()])

    # -- pass 1+2: constraints ---------------------------------------------------------
    def _bounds(self) -> list[cp.Constraint]:
        """Variable bounds; those with ``|bound| >= INFINITE_BOUND`` are left out, those
        with ``|bound| >= LARGE_BOUND`` are kept aside (:attr:`large`)."""
        import scipy.sparse as sp

        lb, ub = self.ocp.bounds()
        out = []
        finite_lb = np.flatnonzero(lb > -LARGE_BOUND)
        finite_ub = np.flatnonzero(ub < LARGE_BOUND)
        n = self.W.size
        for sign, bound in ((-1.0, lb), (1.0, ub)):
            large = np.flatnonzero((np.abs(bound) >= LARGE_BOUND)
                                   & (np.abs(bound) < INFINITE_BOUND))
            if large.size:  # sign w_i − sign b_i <= 0
                A = sp.csr_matrix((np.full(large.size, sign), (np.arange(large.size), large)),
                                  shape=(large.size, n))
                self._large_rows.append(structure.Affine(
                    A, sp.csr_matrix((large.size, 0 if self.P is None else self.P.size)),
                    -sign * bound[large]))
        if finite_lb.size:
            out.append(self.W[finite_lb] >= lb[finite_lb])
        if finite_ub.size:
            out.append(self.W[finite_ub] <= ub[finite_ub])
        return out

    def _affine_expr(self, aff: structure.Affine) -> cp.Expression:
        expr = aff.A @ self.W + aff.c
        if self.P is not None and aff.B.nnz:
            expr = expr + aff.B @ self.P
        return expr

    def _quadratic_expr(self, q: structure.Quadratic) -> cp.Expression:
        value = q.a @ self.W + q.c
        if q.L.size:
            value = value + 0.5 * cp.sum_squares(q.L @ self.W[q.index])
        if self.P is not None and q.M.nnz:
            value = value + (q.M @ self.P) @ self.W
        if q.b is not None and q.b.nnz and self.P is not None:
            value = value + q.b @ self.P
        if q.phi is not None:
            derived = cp.Parameter(name=f"phi{len(self.derived)}")
            self.derived.append((q.phi, derived))
            value = value + derived
        return cp.reshape(value, (), order="F") if value.size == 1 else value

    def _joint_quadratic_row(self, jq: structure.JointQuadratic
                             ) -> tuple[cp.Constraint, float]:
        """``½‖v‖² + aᵀw + bᵀp + c <= 0`` with ``v = L_w w + L_p p + l`` the row about its
        centre; without the affine part the cone ``‖v‖ <= √(−2c)`` (e.g. (5.15b):
        ``‖R (x_k − z_0)‖ <= 1``), whose multiplier is the row's times ``√(−2c)``."""
        v = jq.Lw @ self.W[jq.w_index] + jq.l
        if jq.p_index.size:
            v = v + jq.Lp @ self.P[jq.p_index]
        if jq.linear_free and jq.c < 0:
            radius = float(np.sqrt(-2.0 * jq.c))
            return cp.norm(v, 2) <= radius, 1.0 / radius
        value = 0.5 * cp.sum_squares(v) + jq.c
        if np.any(jq.a):
            value = value + jq.a @ self.W
        if np.any(jq.b):
            value = value + jq.b @ self.P
        return value <= 0, 1.0

    def _quadratic_row(self, row_expr, w_sym, p_sym, where: str
                       ) -> tuple[cp.Constraint, float]:
        """A convex quadratic row: about its centre when it is jointly quadratic in
        ``(w, p)``; otherwise expanded in ``w`` with its parameter part ``φ(p)`` (affine, or
        a derived parameter such as ``−h(x_k)`` in (2.20))."""
        jq = structure.joint_quadratic(row_expr, w_sym, p_sym)
        if jq is not None and jq.w_index.size:
            return self._joint_quadratic_row(jq)
        q = structure.quadratic(row_expr, w_sym, p_sym, where)
        return self._quadratic_expr(q) <= 0, 1.0

    def _affine_part(self, rows: np.ndarray, aff: structure.Affine, kind: str
                     ) -> list[tuple[np.ndarray, cp.Constraint, float]]:
        """``A w + B p + c (<=|==) 0`` without the rows that always hold: inequality rows
        with an infinite offset (``c <= −INFINITE_BOUND``) or no variables and ``c <= 0``."""
        if kind == "eq":
            return [(rows, self._affine_expr(aff) == 0, 1.0)]
        no_p = np.diff(aff.B.indptr) == 0
        empty = (np.diff(aff.A.indptr) == 0) & no_p
        large = np.flatnonzero(no_p & ~empty & (aff.c <= -LARGE_BOUND)
                               & (aff.c > -INFINITE_BOUND))
        if large.size:
            self._large_rows.append(structure.Affine(aff.A[large], aff.B[large], aff.c[large]))
        keep = np.flatnonzero(~((aff.c <= -LARGE_BOUND) & no_p | (empty & (aff.c <= 0))
                                | (aff.c <= -INFINITE_BOUND)))
        if keep.size == 0:
            return []
        if keep.size < rows.size:
            aff = structure.Affine(aff.A[keep], aff.B[keep], aff.c[keep])
        return [(rows[keep], self._affine_expr(aff) <= 0, 1.0)]

    def _lower_block(self, block, w_sym, p_sym
                     ) -> list[tuple[np.ndarray, cp.Constraint, float]]:
        aff = structure.affine(block.expr, w_sym, p_sym, block.name)
        rows = np.arange(block.rows)
        if aff is not None:
            return self._affine_part(rows, aff, block.kind)
        if block.kind == "eq":
            raise ConvexityError(f"block {block.name!r} ({block.tag}, {block.rows} rows): an "
                                 "equality constraint must be affine for the cvxpy backend; "
                                 "this one is nonlinear (use backend='casadi')")
        parts, affine_rows, affine_parts = [], [], []
        for r in range(block.rows):
            row_expr = block.expr[r]
            row_aff = structure.affine(row_expr, w_sym, p_sym, block.name)
            if row_aff is not None:
                affine_rows.append(r)
                affine_parts.append(row_aff)
                continue
            self.conic = True
            con, scale = self._quadratic_row(row_expr, w_sym, p_sym,
                                             f"block {block.name!r}, row {r}")
            parts.append((np.array([r]), con, scale))
        if affine_rows:
            parts += self._affine_part(np.array(affine_rows), _stack(affine_parts), block.kind)
        return parts

    # -- pass 2: cost ------------------------------------------------------------------
    def _lower_cost(self, w_sym, p_sym) -> cp.Expression:
        """The cost; records :attr:`cost_scale`, its largest coefficient."""
        total: cp.Expression | float = 0.0
        self.cost_scale = 0.0
        for k, term in enumerate(self.ocp.cost.terms):
            label = term.label or f"{term.kind}#{k}"
            if term.kind == "smooth":
                total = total + term.coef * self._smooth_cost(term.expr, w_sym, p_sym, label,
                                                              abs(term.coef))
                continue
            aff = structure.affine(term.expr, w_sym, p_sym, label)
            if aff is None:
                raise ConvexityError(f"cost term {label!r} ({term.kind}): its argument must be "
                                     "affine in the decision variables for the cvxpy backend")
            arg = self._affine_expr(aff)
            atom = _ATOMS[term.kind](arg)
            size = float(np.abs(aff.A.data).max(initial=0.0))
            self._record_scale(abs(term.coef) * (size ** 2 if term.kind == "squared2" else size))
            if term.kind == "norm2":
                self.conic = True
            total = total + term.coef * atom
        return total

    def _record_scale(self, value: float) -> None:
        self.cost_scale = max(self.cost_scale, value)

    def _smooth_cost(self, expr, w_sym, p_sym, label: str, coef: float) -> cp.Expression:
        """A quadratic cost term; its parameter-only part is dropped (the reported objective
        is re-evaluated from the declared cost)."""
        q = structure.quadratic(expr, w_sym, p_sym, f"cost term {label!r}")
        self._record_scale(coef * max(float(np.abs(q.a).max(initial=0.0)),
                                      float((q.L ** 2).sum(axis=0).max(initial=0.0)),
                                      float(np.abs(q.M.data).max(initial=0.0))))
        value = q.a @ self.W
        if q.L.size:
            value = value + 0.5 * cp.sum_squares(q.L @ self.W[q.index])
        if self.P is not None and q.M.nnz:
            value = value + (q.M @ self.P) @ self.W
        return value

    # -- pass 3: solver ---------------------------------------------------------------
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
        if status == "infeasible":
            status, message = self._check_infeasible(message)
        if self.large is not None and not (status == "infeasible" or self._within_large()):
            first = "violated them" if status in ("optimal", "optimal_inaccurate") else status
            status, message = _run(self._full_problem(), self.solver_name,
                                   self.solver_options, False)
            message += (f" (with the {self.large.c.size} large bounds/rows |b| >= "
                        f"{LARGE_BOUND:g}; the solve without them: {first})")
        if status in ("failed", "max_iterations", "optimal_inaccurate") \
                and self.cost_scale > BIG_WEIGHT:
            status, message = self._rescaled(status, message)
        elapsed = time.perf_counter() - start
        n = self.W.size
        w = np.asarray(self.W.value, dtype=float).reshape(-1) if self.W.value is not None \
            and status not in ("infeasible", "failed", "max_iterations") else np.full(n, np.nan)
        stats = self.problem.solver_stats
        dual = self._duals() if status in ("optimal", "optimal_inaccurate") else {}
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

    def _check_infeasible(self, message: str) -> tuple[str, str]:
        """Confirm an "infeasible" verdict by solving the feasibility problem (the same
        constraints, no objective): a badly scaled objective (a 1e12 weight) can make a
        solver declare a feasible problem infeasible."""
        if self._feasibility is None:
            self._feasibility = cp.Problem(cp.Minimize(0), self.problem.constraints)
        status, check = _run(self._feasibility, self.solver_name, self.solver_options, False)
        if status in ("optimal", "optimal_inaccurate"):
            return "failed", (f"{message}; but the constraints alone are feasible "
                              f"(feasibility solve: {check}): the verdict is numerical, "
                              "e.g. from badly scaled cost weights")
        return "infeasible", message

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
                                    + [self._affine_expr(self.large) <= 0])
        return self._full

    def _rescaled(self, status: str, message: str) -> tuple[str, str]:
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
        if status == "optimal_inaccurate" and retry != "optimal":
            self.W.value = first  # keep the first answer unless the retry converged
            return status, message
        if retry in ("optimal", "optimal_inaccurate"):
            return "optimal_inaccurate", (f"{message}; solved with the cost scaled by "
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


def _stack(parts: list[structure.Affine]) -> structure.Affine | None:
    """The rows of ``parts`` as one :class:`~balustrade.backends.structure.Affine`
    (``None`` for no parts)."""
    import scipy.sparse as sp

    if not parts:
        return None
    return structure.Affine(sp.vstack([a.A for a in parts]).tocsr(),
                            sp.vstack([a.B for a in parts]).tocsr(),
                            np.concatenate([a.c for a in parts]))


def _run(problem: cp.Problem, solver: str, options: dict, warm_start: bool
         ) -> tuple[str, str]:
    """Solve ``problem``; ``(status, message)`` with the status one of the six of
    :class:`Solution` and the message cvxpy's status and the solver's own words."""
    try:
        with warnings.catch_warnings():  # "Solution may be inaccurate": the status says so
            warnings.simplefilter("ignore", UserWarning)
            problem.solve(solver=solver, warm_start=warm_start, **options)
        cvx_status, error = problem.status, ""
    except cp.error.SolverError as exc:
        cvx_status, error = cp.SOLVER_ERROR, str(exc)
    words = _solver_words(problem, solver)
    message = cvx_status + (f" ({words})" if words else "") + (f": {error}" if error else "")
    status = _STATUS.get(cvx_status, "failed")
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


_ATOMS = {"squared2": cp.sum_squares, "norm1": cp.norm1, "norm2": cp.norm2,
          "norminf": cp.norm_inf, "max": cp.max}


#: cvxpy statuses → :class:`Solution` statuses. Not certified (``*_inaccurate``) infeasibility
#: and unboundedness (a safety-filter OCP is never unbounded when well posed) are "failed",
#: with cvxpy's and the solver's words in ``Solution.message``; iteration and time limits are
#: "max_iterations".
_STATUS = {
    cp.OPTIMAL: "optimal",
    cp.OPTIMAL_INACCURATE: "optimal_inaccurate",
    cp.INFEASIBLE: "infeasible",
    cp.INFEASIBLE_INACCURATE: "failed",
    cp.UNBOUNDED: "failed",
    cp.UNBOUNDED_INACCURATE: "failed",
    cp.USER_LIMIT: "max_iterations",
    cp.SOLVER_ERROR: "failed",
}
