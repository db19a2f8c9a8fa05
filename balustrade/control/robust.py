"""Algorithm 5.2: the robust PCBF safety filter (thesis Section 5.5).

At each step solve (5.15) for ``h_r(x_k)`` and ``ξ*_k``, then (5.16) with the slacks fixed to
``ξ*_k``, and apply ``u_k = v*_0 + κ(x_k − z*_0)``.

Fallbacks (never raise in the loop; each is recorded in ``StepInfo.fallback``):

1. (5.16) fails but (5.15) succeeded → apply the (5.15) optimizer's ``v_0 + κ(x_k − z_0)``,
   feasible for (5.16) by construction: ``"slack_solution"``;
2. (5.15) fails → apply the shifted candidate (5.17) of the last step,
   ``ṽ_0 + κ(x_k − z̃_0)``, which is feasible for (5.15) when ``E`` is RPI (Theorem 5.15):
   ``"candidate"``; the next candidate is built from it;
3. no candidate → the proposed input projected onto ``U``: ``"projected_proposal"``.

A (5.15) that converged to a point whose ``h_r`` is above the candidate's ``h̃`` (beyond
:data:`ABOVE_CANDIDATE_TOL` relative) ended at a worse local solution of the nonconvex NLP
(the candidate is feasible for (5.15), Theorem 5.15): it is treated as a failed (5.15) —
fallback 2, status ``"slack_above_candidate"``, its value recorded as ``values["h_r_local"]``
(never as ``h_r``), the next (5.15) warm-started as before it. Without this, ``h_r`` rose
from 0.118 to 102.6 on one seeded lane-change run in C (issue #16, session 11).

NaN or inf entries of ``u_p`` are read as 0 and the step runs as usual (status
``"non_finite_proposal[_<status>]"``): (5.16) certifies whatever it is given; a non-finite
state → the projected proposal (``"non_finite_state"``) (:mod:`balustrade.control.fallbacks`).

A (5.15) solve that did not converge (``feasible``, the iteration limit, …) is a failed
(5.15) (fallback 2); one that converged to the solver's acceptable tolerances
(``optimal_inaccurate``) is used and flagged in ``StepInfo.uncertified`` and ``status``.

Truncated solves (real-time mode, issue #14 §5: a target with a budget, e.g.
``target="real-time"``; :attr:`~balustrade.backends.Solution.truncated`) are never read as
optimal; ``StepInfo.status`` carries the word ``"truncated"`` in place of their status:

* a truncated (5.16) whose iterate meets the declared constraints within
  :data:`~balustrade.backends.solution.FEASIBILITY_TOL` is applied (its tube and decrease
  constraints hold; only its cost is not certified) and recorded as
  ``StepInfo.uncertified["filter"] = "truncated"``; stopped infeasible, it is a failed
  (5.16): fallback 1;
* a truncated (5.15) is a failed (5.15) (fallback 2, the candidate (5.17)): its cost at a
  feasible iterate only bounds ``h_r`` from above and is recorded as
  ``values["h_r_upper"]``, never as ``h_r`` — the thesis' fallback for a (5.15) without
  its optimum is the candidate, itself such an upper bound (``h_cand``);
* the next solve is warm-started from a feasible truncated iterate (real-time iterations);
  after a (5.16) stopped infeasible, the next one starts from the primal of its step's
  (5.15), as in :mod:`balustrade.control.pcbf` (not from an older converged (5.16)).

Recovery steps (issue #14): a step whose candidate has ``h̃ > 0``, so that it does not
certify ``h_r(x_k) = 0`` (Theorem 5.15: ``h_r(x_k) <= h̃``), solves (5.15) with the attempt
of its retry chain named by ``recovery_target`` first (default ``"recovery"``: the
interior-point retry, :mod:`balustrade.backends.recovery`), then the rest of the chain;
(5.16) then starts from the (5.15) point, as at the first step. Why: while ``h_r > 0`` the
LP-like (5.15) makes the SQP attempts fail after hundreds of iterations (150–240 ms each)
before the interior-point last resort answers (21–50 ms alone); an interior-point (5.16)
point, as a warm start, stops the next SQP (docs/vehicles.md, session 13).
``recovery_target=None`` keeps the chain's order everywhere. The emitted C decides the same
(``<name>_SLACK_LEAD``). The first step (no candidate) is a recovery step too
(:meth:`RobustPCBFSafetyFilter.recovering`), and there (5.16) is led by the same attempt
(:attr:`RobustPCBFSafetyFilter.filter_lead`, ``<name>_FILTER_LEAD``): its SQP attempts fail
there at the optimal cost and the cold interior-point retry answered anyway (session 15).

Recorded values: ``h_r`` (the optimal value of (5.15), read as ``h̃`` of the polished slacks
(:func:`~balustrade.control.robust_steps.polished_slacks`) — never the solver's objective,
whose slightly negative slacks the point does not certify) and ``h_cand`` (``h̃`` of the candidate
(5.17) built at the previous step, an upper bound on ``h_r`` by Theorem 5.15).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from balustrade._checks import as_scalar, as_vector, check_deltas, check_instance, check_norm_order
from balustrade.backends import (
    RECOVERY_TARGET,
    Compiled,
    Solution,
    Target,
    check_recovery_target,
    companion,
    compile,
    recovery_lead,
)
from balustrade.control.base import StepInfo, feasible_truncation, note_solve, outcome
from balustrade.control.deploy import RobustDeployment
from balustrade.control.fallbacks import (
    finite_proposal,
    finite_state,
    note_proposal,
    project,
    projected_proposal,
)
from balustrade.control.robust_steps import Candidate
from balustrade.control.tube_functions import (
    TubeFunctions,
    tube_candidate,
    tube_cost,
    tube_polished,
)
from balustrade.dsl.error_sets import ErrorSet
from balustrade.dsl.policies import as_policy
from balustrade.dsl.sets import Polytope
from balustrade.dsl.system import System
from balustrade.problems.robust import (
    Objective,
    robust_pcbf_filter_problem,
    robust_pcbf_slack_problem,
    robust_sets,
)

#: a converged (5.15) whose ``h_r`` exceeds the candidate's ``h̃`` by more than this times
#: ``1 + h̃`` is a worse local solution: a failed (5.15) (module docstring); the emitted C
#: uses the same value (``<name>_ABOVE_CAND_TOL``, :mod:`balustrade.codegen.emit_robust`).
#: 1e-5: the interior-point solver's accuracy on (5.15), the tolerance by which
#: tests/test_robust.py allows ``h_r`` above ``h_cand``
ABOVE_CANDIDATE_TOL = 1e-5


class RobustPCBFSafetyFilter:
    """Algorithm 5.2 over the compiled problems (5.15) and (5.16) (any backend)."""

    def __init__(self, slack: Compiled, filter: Compiled, system: System, X_E: Polytope,
                 U: Polytope, error: ErrorSet, h_f: Callable, pi_f: Callable,
                 deltas: np.ndarray, alpha_f: float, slack_norm: int | float = 1,
                 U_E: Polytope | None = None,
                 recovery_target: Target | str | None = RECOVERY_TARGET):
        block = "RobustPCBFSafetyFilter"
        check_instance(system, System, f"{block}: system")
        check_instance(X_E, Polytope, f"{block}: X_E")
        check_instance(U, Polytope, f"{block}: U")
        check_instance(error, ErrorSet, f"{block}: error")
        self.slack, self.filter, self.system = slack, filter, system
        self.X_E, self.U, self.error = X_E, U, error
        self.U_E = U_E if U_E is not None else error.tighten_input(U)
        self.h_f, self.pi_f = h_f, as_policy(pi_f, system.nx, system.nu, block)
        d = as_vector(deltas, f"{block}: tightenings deltas", finite=False)
        self.deltas = check_deltas(d, d.size, block)
        self.alpha_f = as_scalar(alpha_f, f"{block}: alpha_f", 0.0, low_open=True)
        self.slack_norm = check_norm_order(slack_norm, f"{block}: slack_norm")
        #: the recovery target (module docstring, "Recovery steps")
        self.recovery_target = check_recovery_target(recovery_target, block)
        # polish, h̃ and candidate as the CasADi functions the C is generated from (C =
        # Python bitwise: balustrade.control.tube_functions); None: numpy
        self._tube = TubeFunctions.build(system, X_E, self.U_E, h_f, self.pi_f, self.deltas,
                                         self.alpha_f, self.slack_norm)
        self.reset()

    @classmethod
    def build(cls, system: System, X: Polytope, U: Polytope, h_f: Callable, pi_f: Callable,
              N: int, deltas: np.ndarray, error: ErrorSet, alpha_f: float = 1e6,
              slack_norm: int | float = 1, objective: Objective | None = None,
              target: Target | str = "auto", slack_target: Target | str | None = None,
              eps: float = 1e-6, U_tight: Polytope | None = None,
              recovery_target: Target | str | None = RECOVERY_TARGET
              ) -> RobustPCBFSafetyFilter:
        """Build and compile (5.15) for ``slack_target`` and (5.16) for ``target`` (targets
        or preset names, e.g. ``target="cvxpy"``).

        Default: ``"auto"`` for both problems: the direct conic backend (``fast-convex``)
        when the problem is convex (a linear system with convex sets and terminal CBF), else
        ``exact``. On CasADi targets, ``slack_target=None`` means ``exact`` for (5.15)
        (:func:`~balustrade.backends.companion`: the SQP needs hundreds of iterations when
        ``h_r > 0``, the LP-like slack problem with quadratic tube/terminal rows is
        degenerate for it); ``robust-sqp`` is the SQP target for (5.16) (more iterations: the
        default limit stops early on tube problems), the one whose C can be emitted; on any
        other backend (5.15) uses ``target``. Tune a target with
        :meth:`~balustrade.backends.Target.with_options`. ``recovery_target``: the attempt
        that leads (5.15) on a recovery step (module docstring; ``None``: none).
        """
        slack = compile(robust_pcbf_slack_problem(system, X, U, h_f, N, deltas, error, alpha_f,
                                                  slack_norm, U_tight),
                        companion(slack_target, target))
        filt = compile(robust_pcbf_filter_problem(system, X, U, h_f, N, deltas, error, eps,
                                                  objective, U_tight), target)
        sets = robust_sets(X, U, error, U_tight)
        return cls(slack, filt, system, sets.X_E, U, error, h_f, pi_f, deltas, alpha_f,
                   slack_norm, sets.U_E, recovery_target)

    def reset(self) -> None:
        self._last_slack: Solution | None = None
        self._last_filter: Solution | None = None
        self.candidate: Candidate | None = None
        self._slack_recovered = False  # the last converged (5.15) was a recovery solve

    def h_r(self, x: np.ndarray) -> tuple[float, Solution]:
        """Solve (5.15) at ``x``: ``(h_r(x), solution)`` (``nan`` if the solve failed); the
        value is ``h̃`` of the polished slacks (:func:`polished_slacks`)."""
        h_r, s, _ = self._solve_slack(x)
        return h_r, s

    @property
    def slack_lead(self) -> int | None:
        """The attempt of the (5.15) chain a recovery step runs first (``None``: the chain in
        its usual order); read from the problem's chain as it is now (a mirrored chain,
        :func:`~balustrade.codegen.mirror_c_retries`, may have dropped it)."""
        return recovery_lead(self.slack, self.recovery_target)

    @property
    def filter_lead(self) -> int | None:
        """The attempt of the (5.16) chain that runs first when there is no candidate (the
        first step; ``None``: the chain in its usual order). There (5.16), started from the
        interior-point (5.15) point, makes both SQP attempts fail with
        ``Search_Direction_Becomes_Too_Small`` at the optimal cost, and the chain's cold
        interior-point retry answers; leading with that retry gives the same answer without
        the two failed attempts (docs/vehicles.md, "Session 15")."""
        return recovery_lead(self.filter, self.recovery_target)

    def recovering(self) -> bool:
        """Whether the next step is a recovery step: the first step (no candidate certifies
        anything yet) or a candidate whose ``h̃`` is positive, so that it does not certify
        ``h_r(x_k) = 0`` (Theorem 5.15: ``h_r(x_k) <= h̃``). On the lane change's first step
        (5.16), started from the interior-point (5.15) point, ends at the interior-point
        solver's acceptable level: ``optimal_inaccurate`` (used, flagged), in Python and in
        the emitted C alike since it reads the solver's own return status (docs/vehicles.md,
        session 13, the acceptable stop in C)."""
        c = self.candidate
        return c is None or tube_cost(self._tube, c.xi, c.xi_N, self.alpha_f,
                                      self.slack_norm) > 0.0

    def _solve_slack(self, x: np.ndarray, lead: int | None = None
                     ) -> tuple[float, Solution, tuple[np.ndarray, float] | None]:
        """:meth:`h_r` and the polished slacks ``(ξ, ξ_N)`` it was computed from (``None``
        if the solve failed), so that a step polishes them once; ``lead``: the attempt of
        the chain that runs first (a recovery step)."""
        extra = {} if lead is None else {"lead": lead}
        # after a (5.15) answered on a recovery step, from the candidate (5.17): the
        # interior-point point stops the SQP of the next step (docs/vehicles.md, session 13)
        warm = self.candidate.as_dict() if self._slack_recovered and \
            self.candidate is not None else self._last_slack
        s = self.slack.solve({"x0": np.asarray(x, dtype=float)}, warm_start=warm, **extra)
        if not s.success:
            return float("nan"), s, None
        xi, xi_N = tube_polished(self._tube, s, self.X_E, self.h_f, self.deltas)
        # h_r from the polished slacks alone: the solver's objective may carry a slightly
        # negative slack (e.g. xi_N = -3.6e-12, times alpha_f) that the point does not certify
        return tube_cost(self._tube, xi, xi_N, self.alpha_f, self.slack_norm), s, (xi, xi_N)

    def _applied(self, x: np.ndarray, z0: np.ndarray, v0: np.ndarray) -> np.ndarray:
        return np.asarray(v0, dtype=float).reshape(-1) + self.error.kappa(x - z0)

    def _make_candidate(self, z: np.ndarray, v: np.ndarray, xi: np.ndarray) -> Candidate:
        return tube_candidate(self._tube, self.system, self.X_E, self.h_f, self.pi_f, self.deltas,
                              z, v, xi, self.U_E)

    def step(self, x: np.ndarray, u_p: np.ndarray) -> tuple[np.ndarray, StepInfo]:
        """One step of Algorithm 5.2 (module docstring); never raises for runtime data."""
        u_p, replaced = finite_proposal(u_p, self.system.nu, "RobustPCBFSafetyFilter.step: u_p")
        x = finite_state(x, self.system.nx, "RobustPCBFSafetyFilter.step: x")
        if x is None:
            return projected_proposal(u_p, self.U)
        u, info = self._step(x, u_p)
        return u, note_proposal(info, replaced)

    def _step(self, x: np.ndarray, u_p: np.ndarray) -> tuple[np.ndarray, StepInfo]:
        info = StepInfo()
        if self.candidate is not None:
            c = self.candidate
            info.values["h_cand"] = tube_cost(self._tube, c.xi, c.xi_N, self.alpha_f,
                                              self.slack_norm)
        lead = self.slack_lead if self.recovering() else None
        h_r, s1, polished = self._solve_slack(x) if lead is None else \
            self._solve_slack(x, lead)
        info.solve_time, info.solutions["slack"] = s1.solve_time, s1
        if not s1.success:
            info.status = f"slack_{outcome(s1)}"
            if feasible_truncation(s1):  # continued next step; its cost bounds h_r only
                self._last_slack = s1
                info.values["h_r_upper"] = max(float(s1.objective), 0.0)
            return self._fallback(x, u_p, info)
        h_cand = info.values.get("h_cand")
        if h_cand is not None and h_r > h_cand + ABOVE_CANDIDATE_TOL * (1.0 + h_cand):
            info.status, info.values["h_r_local"] = "slack_above_candidate", h_r
            return self._fallback(x, u_p, info)
        self._last_slack = s1
        self._slack_recovered = lead is not None
        note_solve(info, "slack", s1.status)   # optimal_inaccurate: h_r flagged, not certified
        info.values["h_r"] = h_r
        xi, xi_N = polished
        # before the first (5.16) and on a recovery step: from the (5.15) point (an
        # interior-point answer of the previous (5.16) stops the SQP: docs/vehicles.md)
        warm = self._last_filter if self._last_filter is not None and lead is None else \
            {"z": s1["z"], "v": s1["v"]}
        # no candidate (the first step): (5.16) leads with the same attempt as (5.15)
        flead = self.filter_lead if self.candidate is None else None
        s2 = self.filter.solve({"x0": x, "u_p": u_p, "xi": xi, "xi_N": xi_N}, warm_start=warm,
                               **({} if flead is None else {"lead": flead}))
        info.solve_time += s2.solve_time
        info.solutions["filter"] = s2
        if s2.success or feasible_truncation(s2):
            self._last_filter = s2
            note_solve(info, "filter", outcome(s2))
            chosen = s2
            info.status = "ok" if not info.uncertified else "_".join(
                f"{k}_{v}" for k, v in info.uncertified.items())
        else:
            chosen, info.status, info.fallback = s1, f"filter_{outcome(s2)}", "slack_solution"
            if s2.truncated:  # stopped infeasible: restart from the (5.15) point next step
                self._last_filter = None
        z = np.asarray(chosen["z"], dtype=float)
        v = np.asarray(chosen["v"], dtype=float).reshape(self.system.nu, -1)
        self.candidate = self._make_candidate(z, v, xi)
        return self._applied(x, z[:, 0], v[:, 0]), info

    def _fallback(self, x: np.ndarray, u_p: np.ndarray, info: StepInfo
                  ) -> tuple[np.ndarray, StepInfo]:
        c = self.candidate
        if c is not None:
            info.fallback = "candidate"
            u = self._applied(x, c.z[:, 0], c.v[:, 0])
            self.candidate = self._make_candidate(c.z, c.v, c.xi)
            return u, info
        info.fallback = "projected_proposal"
        return project(u_p, self.U), info

    def deployment_spec(self) -> RobustDeployment:
        """Algorithm 5.2 for :func:`balustrade.codegen.emit_robust` (one C call per step),
        also a :class:`~balustrade.control.deploy.ProblemsDeployment` of (5.15) and (5.16)
        for :func:`balustrade.codegen.emit_problems`."""
        return RobustDeployment({"slack": self.slack, "filter": self.filter},
                                "Algorithm 5.2, the robust PCBF filter (5.15)+(5.16)",
                                system=self.system, X_E=self.X_E, U=self.U, U_E=self.U_E,
                                h_f=self.h_f, pi_f=self.pi_f, K=self.error.K
                                if self.error.kappa_fn is None else None,
                                deltas=self.deltas, alpha_f=self.alpha_f,
                                slack_norm=self.slack_norm,
                                recovery_target=self.recovery_target)

