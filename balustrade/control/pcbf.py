"""The PCBF safety filter algorithm (thesis Section 2.4, [41]): at each step solve the
slack problem (2.24) for ``h_PB(x_k)`` and ``ξ*``, then the filter (2.23) with the slacks
fixed to ``ξ*``, and apply ``u*_{0|k}``.

Only an optimal solve of (2.24) gives ``h_PB(x_k)`` and the ``ξ*`` that Theorem 2.30 (the
CBF decrease behind the guarantee) is about (SPEC §2.7). So (issue #12):

* ``optimal`` → ``StepInfo.values["h_PB"]``; the algorithm as above;
* ``optimal_inaccurate`` (converged to the solver's acceptable tolerances) → used as above,
  flagged: ``StepInfo.uncertified["slack"]`` and ``StepInfo.status`` name the status, and
  the value is recorded as ``h_PB`` (accurate to those tolerances);
* ``feasible`` (no convergence, a primal-feasible point) with cost ``<= ZERO_TOL`` → optimal
  all the same (``h_PB >= 0`` is a lower bound it attains): used as an optimal solve;
* ``feasible`` with a larger cost → *not* ``h_PB``: its cost is
  recorded as ``values["h_PB_upper"]`` (any feasible point of (2.24) bounds ``h_PB`` from
  above), ``values["h_PB"]`` is ``nan``, and the step is a failed (2.24): fallback 2 below;
  only when there is no plan left are its slacks used in (2.23) (they relax the
  constraints by at least ``ξ*``; ``fallback = "feasible_slack"``).

Truncated solves (real-time mode, issue #14 §5: a target with a budget, e.g.
``target="real-time"``; :attr:`~balustrade.backends.Solution.truncated`). A solve stopped by
its budget is never read as optimal; ``StepInfo.status`` carries the word ``"truncated"``
in place of its status (``Trace.n_truncated`` counts such steps) and:

* a truncated filter (2.23) whose iterate meets the declared constraints within
  :data:`~balustrade.backends.solution.FEASIBILITY_TOL` is applied — its safety
  constraints (the CBF decrease on the fixed slacks) hold, only its closeness to ``u_p`` is
  not certified — and recorded as ``StepInfo.uncertified["filter"] = "truncated"``; one that
  stopped infeasible is a failed (2.23): fallback 1;
* a truncated slack problem (2.24) at a feasible iterate is treated like a ``feasible``
  one: its cost is only an upper bound on ``h_PB`` (``values["h_PB_upper"]``, ``h_PB`` is
  ``nan``), never the optimal ``h_PB`` — the step takes fallback 2, and only without a plan
  are its slacks used as the slack bound of (2.23) (``"feasible_slack"``, flagged
  ``uncertified["slack"] = "truncated"``); at cost ``<= ZERO_TOL`` it is optimal by the
  lower bound ``h_PB >= 0`` (as for ``feasible``; the status still says ``truncated``).
  Stopped infeasible, it is a failed (2.24): fallback 2;
* the next step's solve is warm-started from a truncated iterate that is feasible (primal
  and dual), so the SQP continues where the budget stopped it (real-time iterations); after
  a filter (2.23) stopped infeasible, the next one starts from the primal of that step's
  (2.24), which is feasible for (2.23) by construction (measured on the pendulum with a 1–3
  iteration cap: continuing infeasible iterates drifts into repeated SQP failures, and
  keeping an older converged point as the warm start never catches up).

Fallbacks (never raise in the loop; each is recorded in ``StepInfo.fallback``):

1. (2.23) fails but (2.24) succeeded → apply ``u_{0|k}`` of the (2.24) optimizer, which
   is feasible for (2.23) by construction (SPEC §2.7): ``"slack_solution"``.
2. (2.24) fails or is not converged → apply the next input of the last successful plan
   (shifted solution, as in the recursive-feasibility candidate), ``"shifted_plan"``;
3. no plan left → the proposed input projected onto ``U``: ``"projected_proposal"``
   (or, after a merely ``feasible`` (2.24), the filter on its slacks, ``"feasible_slack"``).

Bad runtime data (:mod:`balustrade.control.fallbacks`): a NaN or inf state → nothing solved,
the projected proposal (``"non_finite_state"``); NaN or inf entries of ``u_p`` → read as 0
and the step runs as usual (status ``"non_finite_proposal[_<status>]"``): (2.23) certifies
whatever proposal it is given, ``u_p`` only enters its cost.

The emitted C step (:func:`balustrade.codegen.emit_pcbf`) takes the same decisions, with
the same warm starts (a converged solution: primal and multipliers; a certified
``feasible`` (2.24): its primal only; (2.23) only from a converged solution), including
the shifted-plan certificate below (``<name>_shift_cert`` is
:meth:`ShiftedCertificate.function <balustrade.control.shifted.ShiftedCertificate.function>`).

Shifted-plan certificate (``shifted_certificate=True``, :mod:`balustrade.control.shifted`):
on a nonconvex (2.24) a local solver can end ``optimal`` at ``h_PB > 0`` although the shifted
last plan meets (2.24) with zero slack, i.e. ``h_PB = 0`` (measured on the obstacle car of
Section 8.3, docs/obstacles.md; the car then entered an obstacle). When (2.24) fails or
reports ``h_PB > eps``, that candidate is checked exactly and, if it qualifies, used as the
(2.24) point of the step (``values["shifted_certificate"] = 1``, the solver's cost in
``values["h_PB_solver"]``).

Certificate first (``certificate_first``, on by default since session 11 whenever the
shifted-plan certificate is, issue #14): the same candidate is checked *before* (2.24) at
every step with a plan. The cost of (2.24), ``α_f ξ_N + Σ_i ‖ξ_i‖`` with
``α_f > 0`` and ``ξ >= 0``, is 0 only with every slack 0, and the candidate (slacks set to
0) meets every row of (2.24) within the certificate's tolerance: ``h_PB(x) = 0`` is then the
global optimum (the lower bound) and ``ξ* = 0``, so the (2.24) solve is skipped exactly.
(2.23) runs with ``ξ* = 0`` from its usual warm start; with ``shifted_retry`` (opt-in,
session 12) a failed attempt is tried once more from the candidate (feasible for (2.23):
``PCBFSafetyFilter._filter_solve``) before the cold retries, by the chain's solver that
``shifted_retry_solver`` names (default the first; session 13); the next (2.24) starts
from the candidate's primal.
The skipped solve is never reported as a solver result: the step's ``StepInfo.status`` is
``"certified"`` (``"certified_filter_<status>"`` when (2.23) did not end optimal),
``values["certificate_first"] = 1``, ``values["h_PB"] = 0``, and
``solutions["slack"]`` is the candidate, a point of (2.24) and not a solver's result: status
``feasible`` (never ``optimal``), solver ``shifted_plan``, 0 iterations. A candidate that
misses a row (e.g. after a step with ``ξ* > 0``, or without a plan) certifies nothing and
(2.24) is solved as usual.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable

import numpy as np

from balustrade._checks import as_scalar, check_instance
from balustrade.backends import Compiled, Solution, Target, compile
from balustrade.backends.casadi_backend import chain_solver_index
from balustrade.control.base import StepInfo, feasible_truncation, note_solve, outcome
from balustrade.control.deploy import PCBFDeployment
from balustrade.control.fallbacks import (
    finite_proposal,
    finite_state,
    note_proposal,
    project,
    projected_proposal,
)
from balustrade.control.shifted import ShiftedCertificate
from balustrade.dsl.sets import Set
from balustrade.dsl.system import System
from balustrade.errors import BalustradeError, SolverError
from balustrade.problems.pcbf import pcbf_filter_problem, pcbf_slack_problem

#: a merely feasible (2.24) point of cost <= ZERO_TOL is optimal (``h_PB >= 0``)
ZERO_TOL = 1e-9


class PCBFSafetyFilter:
    """Closed-loop PCBF filter over two compiled problems (any backend)."""

    def __init__(self, slack: Compiled, filter: Compiled, U: Set, eps: float = 1e-6,
                 warm_start: str = "last", shifted_certificate: bool = True,
                 certificate_first: bool | None = None, shifted_retry: bool = False,
                 shifted_retry_solver: int = 0):
        """``warm_start``: ``"last"`` starts (2.24) from its last accepted solution;
        ``"shifted"`` from the last (2.23) plan shifted by one step (states ``x_1 … x_N, x_N``
        with the first replaced by the measured state, inputs ``u_1 … u_{N−1}, 0``) — the
        recursive-feasibility candidate of the theory. On nonconvex problems (obstacles)
        the local solver can lose the plan from ``"last"`` (docs/obstacles.md).

        ``shifted_certificate`` (default on): when (2.24) fails or reports ``h_PB`` above
        ``eps`` (the relaxation (2.23) adds to every row anyway), the remaining inputs of
        the last applied plan (then zeros), rolled out from ``x``, are checked exactly
        (:class:`~balustrade.control.shifted.ShiftedCertificate`); if they meet (2.24) with
        zero slack, ``h_PB(x) = 0`` is certified by the lower bound and this candidate
        replaces the solver's (local, non-global) point — the invariance of ``S_PB`` then
        holds on nonconvex problems too. Recorded as ``values["shifted_certificate"] = 1``
        and the solver's cost ``values["h_PB_solver"]``.

        ``certificate_first`` (default: on whenever ``shifted_certificate`` is, issue #14
        "defaults must be right"): check that candidate *before* (2.24) and skip the solve
        when it certifies ``h_PB = 0`` (module docstring, "Certificate first"); such a step
        reports the status ``"certified"``, a successful step
        (:func:`~balustrade.control.base.step_succeeded`). ``False`` solves (2.24) at
        every step; ``True`` needs ``shifted_certificate``.

        ``shifted_retry`` (default off, opt-in; on for the obstacle car of Section 8.3,
        :func:`balustrade.reproduce.obstacles.pcbf_algorithm`): in a certified step whose
        (2.23) attempt from its last solution fails, one more attempt from the certified
        shifted plan before the cold retries (:meth:`_filter_solve`). Off by default: on the
        cart-pole ``fast-sqp`` loop the first attempt fails in 56 of 97 certified steps and
        the extra attempt added 50 % (2.23) iterations without changing a decision.

        ``shifted_retry_solver`` (with ``shifted_retry``): which solver of the (2.23) chain
        makes that attempt — 0 (the default) the first solver, ``k`` the ``k``-th retry's,
        ``-1`` the chain's last (``CasadiCompiled.solve(second_solver=)``). On the obstacle
        car (``structured-ip``) ``-1``, the chain's last resort from the plan, cut the worst
        step where the first solver stalls from every start (docs/obstacles.md
        "session 13")."""
        check_instance(U, Set, "PCBFSafetyFilter: U")
        if certificate_first and not shifted_certificate:
            raise BalustradeError("PCBFSafetyFilter: certificate_first=True checks the "
                                  "shifted-plan certificate; it needs "
                                  "shifted_certificate=True")
        if warm_start not in ("last", "shifted"):
            raise BalustradeError(f"PCBFSafetyFilter: warm_start must be 'last' or 'shifted', "
                                  f"got {warm_start!r}")
        self.warm_start = warm_start
        for name, prob in (("slack", slack), ("filter", filter)):
            if not callable(getattr(prob, "solve", None)):
                raise BalustradeError(f"PCBFSafetyFilter: {name} must be a compiled problem "
                                      f"(balustrade.backends.compile), got "
                                      f"{type(prob).__name__}")
        self.slack, self.filter, self.U = slack, filter, U
        # the state size from (2.24)'s parameter x0: a wrong x is named as "step: x"
        x0 = getattr(getattr(slack, "ocp", None), "parameters", {}).get("x0")
        self._nx = None if x0 is None else x0.shape[0]
        self.eps = as_scalar(eps, "PCBFSafetyFilter: eps", low=0.0)
        self.nu = U.dim
        self.certificate = ShiftedCertificate(slack, ZERO_TOL) if shifted_certificate \
            else None
        self.certificate_first = bool(shifted_certificate) if certificate_first is None \
            else bool(certificate_first)
        self.shifted_retry = bool(shifted_retry)
        if isinstance(shifted_retry_solver, bool) or not isinstance(
                shifted_retry_solver, int | np.integer) or shifted_retry_solver < -1:
            raise BalustradeError(f"PCBFSafetyFilter: shifted_retry_solver must be an int "
                                  f">= -1 (0 the first solver, k the k-th retry's, -1 the "
                                  f"last), got {shifted_retry_solver!r}")
        self.shifted_retry_solver = int(shifted_retry_solver)
        retries = getattr(filter, "retries", None)  # the (2.23) chain (CasADi backends)
        if retries is not None:
            try:
                chain_solver_index(self.shifted_retry_solver, len(retries))
            except SolverError as err:
                raise BalustradeError(f"PCBFSafetyFilter: shifted_retry_solver "
                                      f"{shifted_retry_solver} names no attempt of the "
                                      f"(2.23) chain ({len(retries)} retries): {err}") from None
        # whether the (2.23) backend takes a second start (CasadiCompiled.solve); read once
        self._second_start_ok = "second_start" in inspect.signature(
            self.filter.solve).parameters
        self.reset()

    @classmethod
    def build(cls, system: System, X: Set, U: Set, h_f: Callable, N: int,
              deltas: np.ndarray, alpha_f: float = 1e6, slack_norm: int | float = 1,
              target: Target | str = "fast-sqp", eps: float = 1e-6,
              warm_start: str = "last", shifted_certificate: bool = True,
              certificate_first: bool | None = None, shifted_retry: bool = False,
              shifted_retry_solver: int = 0) -> PCBFSafetyFilter:
        """Build and compile both problems ((2.24) and (2.23)) for ``target`` (a
        :class:`~balustrade.backends.Target` or a preset name, e.g. ``"cvxpy"``);
        ``warm_start``, ``shifted_certificate``, ``certificate_first``,
        ``shifted_retry`` and ``shifted_retry_solver`` are passed to the constructor (same
        defaults)."""
        slack = compile(pcbf_slack_problem(system, X, U, h_f, N, deltas, alpha_f, slack_norm),
                        target)
        filt = compile(pcbf_filter_problem(system, X, U, h_f, N, deltas, eps), target)
        return cls(slack, filt, U, eps, warm_start=warm_start,
                   shifted_certificate=shifted_certificate,
                   certificate_first=certificate_first, shifted_retry=shifted_retry,
                   shifted_retry_solver=shifted_retry_solver)

    def reset(self) -> None:
        self._last_slack: Solution | None = None
        self._last_filter: Solution | None = None
        self._plan: np.ndarray | None = None  # inputs of the last successful plan
        self._plan_age = 0

    def step(self, x: np.ndarray, u_p: np.ndarray) -> tuple[np.ndarray, StepInfo]:
        """One step of the algorithm (module docstring); never raises for runtime data."""
        u_p, replaced = finite_proposal(u_p, self.nu, "PCBFSafetyFilter.step: u_p")
        x = finite_state(x, self._nx, "PCBFSafetyFilter.step: x")
        if x is None:
            return projected_proposal(u_p, self.U)
        u, info = self._step(x, u_p)
        return u, note_proposal(info, replaced)

    def _slack_start(self, x: np.ndarray) -> Solution | dict | None:
        """The warm start of (2.24): its last solution, or the shifted last plan."""
        last = self._last_filter
        if self.warm_start != "shifted" or last is None or not last.success:
            return self._last_slack
        X, U = np.asarray(last["x"], dtype=float), np.asarray(last["u"], dtype=float)
        Xs = np.hstack([X[:, 1:], X[:, -1:]])
        Xs[:, 0] = x
        return {"x": Xs, "u": np.hstack([U[:, 1:], np.zeros((U.shape[0], 1))])}

    def _step(self, x: np.ndarray, u_p: np.ndarray) -> tuple[np.ndarray, StepInfo]:
        first = self._first(x)
        if first is not None:
            return self._certified_step(x, u_p, first)
        s1 = self.slack.solve({"x0": x}, warm_start=self._slack_start(x))
        info = StepInfo(solve_time=s1.solve_time, solutions={"slack": s1})
        if feasible_truncation(s1):  # real-time iterations: the next solve continues it
            self._last_slack = s1
        shifted = self._shifted(x, s1)
        if shifted is not None:  # the solver's point is not the global optimum h_PB = 0
            info.values.update(shifted_certificate=1.0, h_PB_solver=float(
                s1.objective) if s1.usable or feasible_truncation(s1) else float("nan"))
            info.solve_time += shifted.solve_time
            info.solutions["slack"] = s1 = shifted  # the (2.24) point the step uses
        if not (s1.usable or feasible_truncation(s1)):
            info.status = f"slack_{outcome(s1)}"
            return self._fallback(u_p, info, "shifted_plan")
        value = max(float(s1.objective), 0.0)
        # h_PB >= 0 (nonnegative slacks and norms): a feasible point of cost <= ZERO_TOL is
        # optimal by that lower bound, converged or not (e.g. the fast-sqp target's zero step
        # at x = 0)
        certified = s1.status == "optimal" or (
            (s1.status == "feasible" or s1.truncated) and value <= ZERO_TOL)
        if not certified:
            note_solve(info, "slack", outcome(s1))
        upper_only = not s1.success and not certified  # feasible, not converged
        if upper_only:
            info.status = f"slack_{outcome(s1)}"
            info.values.update(h_PB=float("nan"), h_PB_upper=value)
            if self._has_shifted_plan():
                return self._fallback(u_p, info, "shifted_plan")
        else:
            self._last_slack = s1
            info.values["h_PB"] = value
        xi = np.maximum(np.asarray(s1["xi"]), 0.0)
        xi_N = max(float(np.asarray(s1["xi_N"]).reshape(-1)[0]), 0.0)
        warm = self._last_filter if self._last_filter is not None and shifted is None \
            else {"x": s1["x"], "u": s1["u"]}
        s2 = self.filter.solve({"x0": x, "u_p": u_p, "xi": xi, "xi_N": xi_N}, warm_start=warm)
        info.solve_time += s2.solve_time
        info.solutions["filter"] = s2
        if s2.success or feasible_truncation(s2):  # a feasible iterate is continued
            self._last_filter = s2
        elif s2.truncated:  # stopped infeasible: restart from the (2.24) point next step
            self._last_filter = None
        if s2.usable or feasible_truncation(s2):
            note_solve(info, "filter", outcome(s2))
            plan = np.asarray(s2["u"]).reshape(self.nu, -1)
            info.status = "ok" if certified and not s1.truncated and s2.status == "optimal" \
                else f"slack_{outcome(s1)}_filter_{outcome(s2)}"
        else:
            info.status = ("" if certified and not s1.truncated else
                           f"slack_{outcome(s1)}_") + f"filter_{outcome(s2)}"
            info.fallback = "slack_solution"
            plan = np.asarray(s1["u"]).reshape(self.nu, -1)
        if upper_only:
            info.fallback = "feasible_slack"
        self._plan, self._plan_age = plan, 0
        return plan[:, 0].copy(), info

    def _first(self, x: np.ndarray) -> Solution | None:
        """Certificate first: the shifted plan as the (2.24) point *before* solving, when
        it certifies ``h_PB = 0`` (then a ``feasible`` :class:`Solution`: a point, not a
        solver's result); ``None`` when the option is off, without a plan or when the
        candidate misses a row or bound of (2.24)."""
        if not self.certificate_first or self.certificate is None or self._plan is None:
            return None
        cand = self.certificate.check(x, self._plan[:, self._plan_age + 1:])
        if cand is None:
            return None
        cand.status = "feasible"
        cand.message = "certificate first: the shifted plan meets (2.24) with zero slack, " \
                       "h_PB = 0 (lower bound); (2.24) not solved"
        return cand

    def _certified_step(self, x: np.ndarray, u_p: np.ndarray, cand: Solution
                        ) -> tuple[np.ndarray, StepInfo]:
        """A step whose (2.24) is skipped: ``h_PB = 0``, ``ξ* = 0``; (2.23) from its usual
        warm start (its last accepted solution, else the candidate's states and inputs) —
        with ``shifted_retry``, a failed attempt from the last solution is tried once more
        from the candidate before the cold retries (:meth:`_filter_solve`); the next (2.24)
        starts from the candidate's primal."""
        info = StepInfo(solve_time=cand.solve_time, solutions={"slack": cand})
        info.values.update(h_PB=max(float(cand.objective), 0.0), certificate_first=1.0)
        self._last_slack = cand
        xi = np.maximum(np.asarray(cand["xi"]), 0.0)
        xi_N = max(float(np.asarray(cand["xi_N"]).reshape(-1)[0]), 0.0)
        start = {"x": cand["x"], "u": cand["u"]}
        params = {"x0": x, "u_p": u_p, "xi": xi, "xi_N": xi_N}
        if self._last_filter is None:
            s2 = self.filter.solve(params, warm_start=start)
        elif not self.shifted_retry:
            s2 = self.filter.solve(params, warm_start=self._last_filter)
        else:
            s2 = self._filter_solve(params, self._last_filter, start)
        info.solve_time += s2.solve_time
        info.solutions["filter"] = s2
        if s2.success or feasible_truncation(s2):
            self._last_filter = s2
        elif s2.truncated:
            self._last_filter = None
        info.status = "certified" if s2.status == "optimal" and not s2.truncated \
            else f"certified_filter_{outcome(s2)}"
        if s2.usable or feasible_truncation(s2):
            note_solve(info, "filter", outcome(s2))
            plan = np.asarray(s2["u"]).reshape(self.nu, -1)
        else:  # the candidate is feasible for (2.23) (its slacks are 0 <= xi* + eps)
            info.fallback = "slack_solution"
            plan = np.asarray(cand["u"]).reshape(self.nu, -1)
        self._plan, self._plan_age = plan, 0
        return plan[:, 0].copy(), info

    def _filter_solve(self, params: dict, warm: Solution, plan: dict) -> Solution:
        """(2.23) of a certified step from its last solution; if that attempt fails, from
        the certified shifted plan ``plan`` before the cold retries (issue #16, session 12).

        The plan meets every row and bound of (2.24) with zero slack (it is the certificate
        of ``h_PB = 0``), so ``ξ* = 0`` and it meets every row of (2.23), whose rows are
        those of (2.24) with the slacks fixed to ``ξ* + eps`` (SPEC §2.7: the optimizer of
        (2.24) is feasible for (2.23)); (2.23) has no decrease or ``h_PB`` row. A feasible
        start can be a better second try than the cold one (the obstacle car on the
        structured-ip target, docs/obstacles.md "session 12": 2 failing chains removed; the
        extra attempt itself fails at 2 of the 5 steps where it runs, and where it fails it
        adds an attempt, ~0.1 s at the worst step). Only with ``shifted_retry`` (opt-in).
        Backends whose ``solve`` has no ``second_start`` run their usual chain."""
        if self._second_start_ok:
            if self.shifted_retry_solver:
                return self.filter.solve(params, warm_start=warm, second_start=plan,
                                         second_solver=self.shifted_retry_solver)
            return self.filter.solve(params, warm_start=warm, second_start=plan)
        return self.filter.solve(params, warm_start=warm)

    def _shifted(self, x: np.ndarray, s1: Solution) -> Solution | None:
        """The shifted plan as a certified optimum of (2.24) when the solve did not certify
        ``h_PB = 0`` itself (``None`` otherwise or when the plan does not qualify)."""
        if self.certificate is None or self._plan is None:
            return None
        if (s1.usable or feasible_truncation(s1)) and float(s1.objective) <= max(
                ZERO_TOL, self.eps):
            return None  # h_PB = 0, or within the relaxation eps that (2.23) adds anyway
        return self.certificate.check(x, self._plan[:, self._plan_age + 1:])

    def _has_shifted_plan(self) -> bool:
        """The last successful plan has an input left for the next step."""
        return self._plan is not None and self._plan_age + 1 < self._plan.shape[1]

    def _fallback(self, u_p: np.ndarray, info: StepInfo, kind: str
                  ) -> tuple[np.ndarray, StepInfo]:
        if kind == "shifted_plan" and self._has_shifted_plan():
            self._plan_age += 1
            info.fallback = "shifted_plan"
            return self._plan[:, self._plan_age].copy(), info
        info.fallback = "projected_proposal"
        return project(u_p, self.U), info

    def deployment_spec(self) -> PCBFDeployment:
        """What the emitted C step needs (:func:`balustrade.codegen.emit_pcbf`): both
        compiled problems, ``U``, ``eps`` and :data:`ZERO_TOL`."""
        if self.warm_start != "last":
            raise BalustradeError("PCBFSafetyFilter.deployment_spec: the emitted C starts (2.24) "
                                  "from its last solution; build the filter with "
                                  "warm_start='last' to emit it")
        return PCBFDeployment(slack=self.slack, filter=self.filter, U=self.U,
                              eps=float(self.eps), zero_tol=ZERO_TOL,
                              shifted_certificate=self.certificate is not None,
                              certificate_first=self.certificate_first,
                              shifted_retry=self.shifted_retry,
                              shifted_retry_solver=self.shifted_retry_solver)
