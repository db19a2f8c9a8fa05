"""Lowering of an :class:`~balustrade.dsl.ocp.OCP` to a DPP-parametrized cvxpy problem.

Passes: (1) classify every block row as affine or convex quadratic
(:mod:`balustrade.backends.structure`), refusing anything else with an error naming the
block; (2) build one decision vector ``W`` and one parameter vector ``P`` and the cvxpy
atoms; (3) pick the solver (PIQP for LPs/QPs, Clarabel for SOCPs) unless one is given.
The compiled problem is re-solved with new parameter values without rebuilding.
"""

from __future__ import annotations

import time

import cvxpy as cp
import numpy as np

from balustrade.backends import structure
from balustrade.backends.solution import Solution
from balustrade.dsl.ocp import OCP
from balustrade.errors import ConvexityError, SolverError

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
        self.block_constraints: dict[str, list[tuple[np.ndarray, cp.Constraint]]] = {}
        constraints: list[cp.Constraint] = []
        for block in ocp.blocks:
            parts = self._lower_block(block, w_sym, p_sym)
            self.block_constraints[block.name] = parts
            constraints += [c for _, c in parts]
        lb, ub = ocp.bounds()
        self.bound_constraints = []
        finite_lb, finite_ub = np.flatnonzero(np.isfinite(lb)), np.flatnonzero(np.isfinite(ub))
        if finite_lb.size:
            self.bound_constraints.append(self.W[finite_lb] >= lb[finite_lb])
        if finite_ub.size:
            self.bound_constraints.append(self.W[finite_ub] <= ub[finite_ub])
        objective = self._lower_cost(w_sym, p_sym)
        self.problem = cp.Problem(cp.Minimize(objective), constraints + self.bound_constraints)
        if (self.P is not None or self.derived) and not self.problem.is_dpp():
            raise ConvexityError(f"{ocp.name}: parameters enter the problem in a way that is not "
                                 "DPP (disciplined parametrized); check parameter products")
        self.solver_name = self._choose_solver(solver)
        self.solver_options = {**SOLVER_OPTIONS.get(self.solver_name, {}), **(options or {})}
        import casadi as ca

        self._objective = ca.Function("objective", [w_sym, p_sym], [ocp.cost.expr()])

    # -- pass 1+2: constraints ---------------------------------------------------------
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

    def _lower_block(self, block, w_sym, p_sym) -> list[tuple[np.ndarray, cp.Constraint]]:
        aff = structure.affine(block.expr, w_sym, p_sym, block.name)
        rows = np.arange(block.rows)
        if aff is not None:
            e = self._affine_expr(aff)
            return [(rows, e == 0 if block.kind == "eq" else e <= 0)]
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
            q = structure.quadratic(row_expr, w_sym, p_sym, f"block {block.name!r}, row {r}")
            self.conic = True
            parts.append((np.array([r]), self._quadratic_expr(q) <= 0))
        if affine_rows:
            import scipy.sparse as sp

            stacked = structure.Affine(sp.vstack([a.A for a in affine_parts]).tocsr(),
                                       sp.vstack([a.B for a in affine_parts]).tocsr(),
                                       np.concatenate([a.c for a in affine_parts]))
            parts.append((np.array(affine_rows), self._affine_expr(stacked) <= 0))
        return parts

    # -- pass 2: cost ------------------------------------------------------------------
    def _lower_cost(self, w_sym, p_sym) -> cp.Expression:
        total: cp.Expression | float = 0.0
        for k, term in enumerate(self.ocp.cost.terms):
            label = term.label or f"{term.kind}#{k}"
            if term.kind == "smooth":
                total = total + term.coef * self._smooth_cost(term.expr, w_sym, p_sym, label)
                continue
            aff = structure.affine(term.expr, w_sym, p_sym, label)
            if aff is None:
                raise ConvexityError(f"cost term {label!r} ({term.kind}): its argument must be "
                                     "affine in the decision variables for the cvxpy backend")
            arg = self._affine_expr(aff)
            atom = _ATOMS[term.kind](arg)
            if term.kind == "norm2":
                self.conic = True
            total = total + term.coef * atom
        return total

    def _smooth_cost(self, expr, w_sym, p_sym, label: str) -> cp.Expression:
        """A quadratic cost term; its parameter-only part is dropped (the reported objective
        is re-evaluated from the declared cost)."""
        q = structure.quadratic(expr, w_sym, p_sym, f"cost term {label!r}")
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
              warm_start: object | None = None) -> Solution:
        """Solve with the given parameter values (warm starts are the solver's own)."""
        p = self.ocp.pack_parameters(params)
        if self.P is not None:
            self.P.value = p
        for phi, param in self.derived:
            param.value = float(phi(p))
        start = time.perf_counter()
        message = ""
        try:
            self.problem.solve(solver=self.solver_name, warm_start=True,
                               **self.solver_options)
            status = _status(self.problem.status)
        except cp.error.SolverError as exc:
            status, message = "failed", str(exc)
        elapsed = time.perf_counter() - start
        n = self.W.size
        w = np.asarray(self.W.value, dtype=float).reshape(-1) if self.W.value is not None \
            and status != "infeasible" else np.full(n, np.nan)
        stats = self.problem.solver_stats
        dual = self._duals() if status in ("optimal", "optimal_inaccurate") else {}
        objective = float(self._objective(w, p)) if np.all(np.isfinite(w)) else np.nan
        return Solution(status=status, objective=objective,
                        primal=self.ocp.unpack_variables(w), dual=dual,
                        solve_time=elapsed,
                        iterations=int(getattr(stats, "num_iters", 0) or 0) if stats else 0,
                        backend="cvxpy", solver=self.solver_name, w=w, p=p,
                        message=message or str(self.problem.status))

    def _duals(self) -> dict[str, np.ndarray]:
        out = {}
        for block in self.ocp.blocks:
            values = np.zeros(block.rows)
            for rows, con in self.block_constraints[block.name]:
                if con.dual_value is not None:
                    values[rows] = np.asarray(con.dual_value, dtype=float).reshape(-1)
            out[block.name] = values
        return out


_ATOMS = {"squared2": cp.sum_squares, "norm1": cp.norm1, "norm2": cp.norm2,
          "norminf": cp.norm_inf, "max": cp.max}


def _status(status: str) -> str:
    return {
        cp.OPTIMAL: "optimal",
        cp.OPTIMAL_INACCURATE: "optimal_inaccurate",
        cp.INFEASIBLE: "infeasible",
        cp.INFEASIBLE_INACCURATE: "infeasible",
        cp.UNBOUNDED: "failed",
        cp.UNBOUNDED_INACCURATE: "failed",
    }.get(status, "failed")
