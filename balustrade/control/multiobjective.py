"""Algorithms 6.3 (multiobjective Lyapunov) and 6.4 (multiobjective robust PCBF).

**Algorithm 6.3** (:class:`MultiobjectiveLyapunovController`, linear design (6.10)): at ``k = 0``
solve (6.3) without (6.3h) for a feasible ``ũ_0`` (SPEC [Default]); then at every step solve
(6.10) with ``bound = V((x_k, ũ_k)) − (1 − ρ) l(x_k, ũ_{0|k})``, apply ``ṽ_{0|k}``, measure
``w_k = x_{k+1} − A x_k − B u_k`` and set ``ũ_{k+1} = ξ(x_{k+1}, ṽ_k, w_k)`` by the switching rule
(6.6)/(6.7). Fallback when (6.10) fails: apply the warm start ``ũ_k`` itself, which satisfies
(6.3b–h) (Assumption 6.7.2–3): ``"warm_start"``.

**Algorithm 6.4** (:class:`MultiobjectivePCBFController`): at ``k = 0`` solve (5.15) and set
``ξ̃_0 = ξ*``, ``ξ*_{−1} = ξ̃_0``; at every step solve (6.15) with
``bound = (1−ρ) h̃(ξ̃_k) + ρ h̃(ξ*_{k−1})``, apply ``v_0 + κ(x_k − z_0)``, build ``ξ̃_{k+1}`` by
(6.14) and store ``ξ*_k``. Fallback when (6.15) fails: apply the warm-start candidate (6.14)
``(z̃, ṽ, ξ̃)``, feasible for (6.15) when ``E`` is RPI (Theorem 6.15): ``"warm_start"``. A
converged (6.15) whose plan needs more than the bound (its polished slacks' ``h̃`` above it
by more than :data:`DECREASE_TOL` relative) is no feasible point of (6.15) and falls back
the same way (status ``"problem_above_bound"``, value ``h_tilde_rejected``).

Recovery steps (issue #14): the first (5.15) and every (6.15) until one converges (the
bound of the first leaves no interior: the minimizers of (5.15)) run the attempt of their
retry chains named by ``recovery_target`` first (default ``"recovery"``: the interior-point
retry, :mod:`balustrade.backends.recovery`), then the rest of the chain; the (6.15) after a
recovery solve, and each next one until one converges, starts from the candidate (6.14),
not from the interior-point point, which stops the SQP (docs/vehicles.md, session 13).
``recovery_target=None``: the usual order. The emitted C decides the same
(``<name>_SLACK_LEAD``, ``<name>_PROBLEM_LEAD``). Ordinary (6.15) solves start from the
previous converged (6.15) (primal and multipliers); ``candidate_duals=True`` (opt-in, CasADi
problems) starts them from the candidate (6.14) with the previous multipliers instead
(``<name>_CANDIDATE_DUALS`` in C; measured on the lane change in docs/vehicles.md,
"Session 14").

The decrease bounds get a margin ``bound_tol · max(1, bound)`` (default ``1e-9``) so that a
candidate that meets them with equality is not declared infeasible by solver round-off.
A solve used although it ended ``optimal_inaccurate`` is flagged in ``StepInfo.uncertified``.
NaN or inf entries of ``u_p`` (which only enters the costs) are read as 0 and the step runs
as usual (status ``"non_finite_proposal[_<status>]"``); a non-finite state → the projected
proposal (``"non_finite_state"``) (:mod:`balustrade.control.fallbacks`).
Recorded values: 6.3 — ``V`` (``V((x_k, ṽ_k))``), ``V_bound``; 6.4 — ``h_tilde``
(``h̃(ξ*_k)``), ``bound``, ``h_cand`` (``h̃(ξ̃_k)``) and, with ``record_h_r=True``, ``h_r``
(an extra (5.15) solve, not counted in ``solve_time``; solved again from the candidate
when its value exceeds ``h_cand``, which no minimum can; NaN if still above).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from balustrade._checks import as_scalar, check_instance
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
from balustrade.control.base import StepInfo, note_solve, outcome
from balustrade.control.deploy import LyapunovDeployment, MultiobjectiveDeployment
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
from balustrade.errors import BalustradeError
from balustrade.problems.multiobjective import (
    LinearLyapunovDesign,
    decrease_bound,
    multiobjective_lyapunov_problem,
    multiobjective_pcbf_problem,
)
from balustrade.problems.robust import Objective, robust_pcbf_slack_problem, robust_sets


class MultiobjectiveLyapunovController:
    """Algorithm 6.3 for the linear design (6.10)."""

    def __init__(self, design: LinearLyapunovDesign, problem: Compiled, init: Compiled,
                 rho: float = 0.5, bound_tol: float = 1e-9):
        self.rho = as_scalar(rho, "Algorithm 6.3: rho (ρ)", 0.0, 1.0, high_open=True)
        self.bound_tol = as_scalar(bound_tol, "Algorithm 6.3: bound_tol", 0.0)
        check_instance(design, LinearLyapunovDesign, "Algorithm 6.3: design")
        self.design, self.problem, self.init = design, problem, init
        self.reset()

    @classmethod
    def build(cls, design: LinearLyapunovDesign, rho: float = 0.5,
              objective: Objective | None = None, target: Target | str = "exact"
              ) -> MultiobjectiveLyapunovController:
        """Build and compile (6.10) and its initialization for ``target`` (a
        :class:`~balustrade.backends.Target` or a preset name, e.g. ``"cvxpy"``)."""
        prob = compile(multiobjective_lyapunov_problem(design, True, objective), target)
        init = compile(multiobjective_lyapunov_problem(design, False, name="mo_lyap_init"),
                       target)
        return cls(design, prob, init, rho)

    def reset(self) -> None:
        self.u_tilde: np.ndarray | None = None
        self._prev: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # x, u, ṽ

    def step(self, x: np.ndarray, u_p: np.ndarray) -> tuple[np.ndarray, StepInfo]:
        """One step of Algorithm 6.3 (module docstring); never raises for runtime data."""
        d = self.design
        where = "Algorithm 6.3 (MultiobjectiveLyapunovController.step: "
        u_p, replaced = finite_proposal(u_p, d.system.nu, where + "u_p)")
        x = finite_state(x, d.system.nx, where + "x)")
        if x is None:
            return projected_proposal(u_p, d.U)
        u, info = self._step(x, u_p)
        return u, note_proposal(info, replaced)

    def _step(self, x: np.ndarray, u_p: np.ndarray) -> tuple[np.ndarray, StepInfo]:
        d = self.design
        nu = d.system.nu
        info = StepInfo()
        if self._prev is None:
            s0 = self.init.solve({"x0": x, "u_p": u_p})
            info.solve_time += s0.solve_time
            if not s0.success:
                info.status = f"init_{outcome(s0)}"
                info.fallback = "projected_proposal"
                return project(u_p, d.U), info
            note_solve(info, "init", s0.status)
            self.u_tilde = np.asarray(s0["v"], dtype=float).reshape(nu, -1)
            info.values["switch"] = 0.0
        else:
            x_prev, u_prev, v_prev = self._prev
            w = x - d.system.A @ x_prev - d.system.B @ u_prev
            self.u_tilde, rule = d.switch(x, v_prev, w)
            info.values["switch"] = 1.0 if rule == "xi_f" else 0.0
        bound = d.bound(x, self.u_tilde, self.rho)
        bound += self.bound_tol * max(1.0, abs(bound))
        info.values["V_bound"] = bound
        sol = self.problem.solve({"x0": x, "u_p": u_p, "bound": bound},
                                 warm_start={"v": self.u_tilde,
                                             "z": d.rollout(x, self.u_tilde)})
        info.solve_time += sol.solve_time
        info.solutions["problem"] = sol
        if sol.success:
            v = np.asarray(sol["v"], dtype=float).reshape(nu, -1)
            note_solve(info, "problem", sol.status)   # optimal_inaccurate: flagged only
            info.status = "ok"
        else:
            v = self.u_tilde
            info.status, info.fallback = f"problem_{outcome(sol)}", "warm_start"
        info.values["V"] = d.V(x, v)
        u = v[:, 0].copy()
        self._prev = (x, u, v)
        return u, info

    def deployment_spec(self) -> LyapunovDeployment:
        """Algorithm 6.3 for :func:`balustrade.codegen.emit_mo_lyap.emit_mo_lyapunov` (one C
        call per step), also a :class:`~balustrade.control.deploy.ProblemsDeployment` of
        (6.10) and its initialization (6.3) for :func:`balustrade.codegen.emit_problems`."""
        d = self.design
        return LyapunovDeployment(
            {"problem": self.problem, "init": self.init},
            "Algorithm 6.3, the multiobjective Lyapunov controller",
            A=d.system.A, B=d.system.B, K=d.K, Q=d.Q, R=d.R, P=d.P, N=d.N, Xf=d.Xf,
            Xs=tuple(d.Xs[:d.N]), Us=tuple(d.Us[:d.N]), Xf_N=d.Xf_N, U=d.U, rho=self.rho,
            bound_tol=self.bound_tol)


#: Algorithm 6.4: how far above the bound of (6.15g) the ``h̃`` of a converged (6.15)'s
#: polished slacks may be, relative (``·max(1, |bound|)``), before the solve counts as failed
#: (:meth:`MultiobjectivePCBFController._meets_decrease`). A threshold the applied plan must
#: meet, not a bound derived for any solver's answer: its value is the SQP's primal tolerance
#: ``tol_pr`` (1e-9), reused as a number. What backs it is measured: the largest rise of an
#: honest answer (the running sums' rounding, the chain's answers within their tolerances)
#: seen on the lane change and the §5.6 example was 3.6e-11, well below it; the
#: ``α_f``-weighted terminal-slack error behind the +3.6e-6 of seeds 42 and 43 is far above.
DECREASE_TOL = 1e-9
#: Algorithm 6.4's default margin of the (6.15g) bound, relative (``bound_tol``)
BOUND_TOL = 1e-9
#: how much ``h̃(ξ*_k)`` can exceed ``h̃(ξ*_{k−1})``, relative (``·max(1, h̃(ξ*_{k−1}))``),
#: with the default margins: ``h_cand <= h̃(ξ*_{k−1})`` (Theorem 6.15), so the bound is at most
#: ``h̃(ξ*_{k−1})`` plus ``BOUND_TOL``, and an applied plan meets it within ``DECREASE_TOL``
H_TILDE_RISE_TOL = BOUND_TOL + DECREASE_TOL


def _check_candidate_options(candidate_duals: object, candidate_second: object) -> None:
    """Both options are bools, and not both on (``candidate_duals`` starts every ordinary
    (6.15) from the candidate already, so ``candidate_second`` would never run): refused
    before anything is compiled."""
    check_instance(candidate_duals, bool, "Algorithm 6.4: candidate_duals")
    check_instance(candidate_second, bool, "Algorithm 6.4: candidate_second")
    if candidate_duals and candidate_second:
        raise BalustradeError("Algorithm 6.4: candidate_duals and candidate_second exclude "
                              "each other (candidate_duals already starts every ordinary "
                              "(6.15) from the candidate); choose one")


class MultiobjectivePCBFController:
    """Algorithm 6.4 over the compiled (5.15) (initialization) and (6.15)."""

    def __init__(self, slack: Compiled, problem: Compiled, system: System, X_E: Polytope,
                 U: Polytope, U_E: Polytope, error: ErrorSet, h_f: Callable, pi_f: Callable,
                 deltas: np.ndarray, alpha_f: float, rho: float = 0.9,
                 bound_tol: float = BOUND_TOL, record_h_r: bool = False,
                 recovery_target: Target | str | None = RECOVERY_TARGET,
                 candidate_duals: bool = False, candidate_second: bool = False):
        rho = as_scalar(rho, "Algorithm 6.4: rho (ρ)", 0.0, 1.0, high_open=True)
        bound_tol = as_scalar(bound_tol, "Algorithm 6.4: bound_tol", 0.0)
        alpha_f = as_scalar(alpha_f, "Algorithm 6.4: alpha_f", 0.0, low_open=True)
        check_instance(system, System, "Algorithm 6.4: system")
        check_instance(error, ErrorSet, "Algorithm 6.4: error")
        self.slack, self.problem, self.system = slack, problem, system
        self.X_E, self.U, self.U_E, self.error = X_E, U, U_E, error
        self.h_f, self.pi_f = h_f, as_policy(pi_f, system.nx, system.nu, "Algorithm 6.4")
        self.deltas = np.asarray(deltas, dtype=float).reshape(-1)
        self.alpha_f, self.rho, self.bound_tol = alpha_f, rho, bound_tol
        self.record_h_r = record_h_r
        #: ordinary steps start (6.15) from the candidate (6.14) with the previous (6.15)'s
        #: multipliers (``True``; CasADi problems only) instead of from the previous (6.15)
        #: itself (``False``, the default): on the lane change (C, 50 seeds) 1 fallback
        #: instead of 6 but twice the steps >= 1 s (docs/vehicles.md, "Session 14")
        _check_candidate_options(candidate_duals, candidate_second)
        self.candidate_duals = candidate_duals
        #: a failed ordinary (6.15) (started from the previous one) is tried once more from
        #: the candidate (6.14) with the previous (6.15)'s multipliers before the cold
        #: retries (``True``; CasADi problems, without ``candidate_duals``): on the lane
        #: change (C, 50 seeds) half the steps >= 1 s, but as many fallbacks (4 new) and a
        #: worse worst step (docs/vehicles.md, "Session 14")
        self.candidate_second = candidate_second
        #: the recovery target (module docstring, "Recovery steps")
        self.recovery_target = check_recovery_target(recovery_target, "Algorithm 6.4")
        # polish, h̃ and candidate as the CasADi functions the C is generated from (C =
        # Python bitwise: balustrade.control.tube_functions); None: numpy
        self._tube = TubeFunctions.build(system, X_E, U_E, h_f, self.pi_f, self.deltas, alpha_f,
                                         1)
        self.reset()

    @classmethod
    def build(cls, system: System, X: Polytope, U: Polytope, h_f: Callable, pi_f: Callable,
              N: int, deltas: np.ndarray, error: ErrorSet, alpha_f: float = 1e6,
              rho: float = 0.9, objective: Objective | None = None,
              target: Target | str = "auto", slack_target: Target | str | None = None,
              U_tight: Polytope | None = None, record_h_r: bool = False,
              running_sum: bool = False,
              recovery_target: Target | str | None = RECOVERY_TARGET,
              candidate_duals: bool = False, candidate_second: bool = False
              ) -> MultiobjectivePCBFController:
        """Build and compile (5.15) (ℓ1 slack norm) for ``slack_target`` and (6.15) for
        ``target`` (targets or preset names; default ``"auto"``: the direct conic backend
        for convex problems, else ``exact``; ``slack_target=None``: ``"exact"`` on
        CasADi, ``target`` on any other backend, see
        :func:`~balustrade.backends.companion`).

        ``running_sum=True``: write (6.15g) through running sums of the slacks
        (:func:`~balustrade.problems.multiobjective.multiobjective_pcbf_problem`; the same
        minimizers, no row touching every slack). On the SQP target (``robust-sqp``) of the
        lane change it makes a (6.15) solve ≈ 18× faster (docs/vehicles.md); on the 2-D
        example of §5.6 the SQP alone then converges less often from far-off states at
        ``k = 0`` (5 of 49 instead of 40; the retry chain's last resort solves them), so it
        is not the default. ``recovery_target``: the attempt that leads the first (5.15)
        and (6.15) solves (module docstring; ``None``: none)."""
        _check_candidate_options(candidate_duals, candidate_second)
        slack = compile(robust_pcbf_slack_problem(system, X, U, h_f, N, deltas, error, alpha_f,
                                                  1, U_tight), companion(slack_target, target))
        prob = compile(multiobjective_pcbf_problem(system, X, U, h_f, N, deltas, error, alpha_f,
                                                   objective, U_tight,
                                                   running_sum=running_sum), target)
        sets = robust_sets(X, U, error, U_tight)
        return cls(slack, prob, system, sets.X_E, U, sets.U_E, error, h_f, pi_f, deltas,
                   alpha_f, rho, record_h_r=record_h_r, recovery_target=recovery_target,
                   candidate_duals=candidate_duals, candidate_second=candidate_second)

    def reset(self) -> None:
        self.candidate: Candidate | None = None
        self.h_prev: float | None = None   # h̃(ξ*_{k−1})
        self._last: Solution | None = None
        self._last_slack: Solution | None = None
        self._recovered = False   # no (6.15) converged since a recovery solve

    def h_tilde(self, xi: np.ndarray, xi_N: float) -> float:
        return tube_cost(self._tube, xi, xi_N, self.alpha_f, 1)

    def _h_r(self, x: np.ndarray, start: dict | None = None, lead: int | None = None
             ) -> Solution:
        extra = {} if lead is None else {"lead": lead}
        s = self.slack.solve({"x0": x}, warm_start=self._last_slack if start is None
                             else start, **extra)
        if s.success:
            self._last_slack = s
        return s

    def _record_h_r(self, x: np.ndarray, info: StepInfo) -> float:
        """``h_r(x_k)`` for the record (``record_h_r``, not used by the algorithm): (5.15)
        from its previous solution. The candidate (6.14) is feasible in (5.15) at ``x_k``
        (Theorem 6.15), so a value above its ``h̃`` is no minimum but a local solution of the
        nonconvex (5.15) (seen on the lane change: 29.6 against ``h̃`` = 0.038 from step
        751 of a 1000-step run, docs/vehicles.md). Then (5.15) is solved again from the
        candidate; if that is no better either, NaN is recorded."""
        c = self.candidate
        limit = self.h_tilde(c.xi, c.xi_N)
        limit += 1e-6 * max(1.0, limit)
        s_r = self._h_r(x)
        h = self._slack_value(s_r)
        if not h <= limit:                                 # also NaN: a failed solve
            again = self._h_r(x, start=c.as_dict())
            h_again = self._slack_value(again)
            if h_again < h or np.isnan(h):
                s_r, h = again, h_again
        if s_r.success:
            note_solve(info, "slack", s_r.status)
        return h if h <= limit else np.nan

    def _slack_value(self, s: Solution) -> float:
        """``h̃`` of a (5.15) solution's polished slacks; NaN if the solve failed."""
        if not s.success:
            return np.nan
        return self.h_tilde(*tube_polished(self._tube, s, self.X_E, self.h_f, self.deltas))

    def _make_candidate(self, z: np.ndarray, v: np.ndarray, xi: np.ndarray) -> Candidate:
        return tube_candidate(self._tube, self.system, self.X_E, self.h_f, self.pi_f,
                              self.deltas, z, v, xi, self.U_E)

    def _candidate_start(self, c: Candidate) -> dict[str, np.ndarray]:
        """The candidate (6.14) as a starting point of (6.15); with the running-sum form of
        (6.15g) also its running sums ``σ_i = Σ_{j<=i} 1ᵀξ̃_j`` (the emitted C computes the
        same, ``bal/multiobj.c``)."""
        start = c.as_dict()
        ocp = getattr(self.problem, "ocp", None)
        if ocp is not None and "xi_sum" in ocp.variables:
            xi = np.asarray(c.xi, dtype=float).reshape(self.X_E.H.shape[0], -1, order="F")
            # σ_i summed entry by entry, column by column, as the C does (bitwise equal)
            sums, acc = np.empty((1, xi.shape[1])), 0.0
            for i in range(xi.shape[1]):
                for value in xi[:, i]:
                    acc += float(value)
                sums[0, i] = acc
            start["xi_sum"] = sums
        return start

    @property
    def slack_lead(self) -> int | None:
        """The attempt of the (5.15) chain the first step runs first (``None``: none)."""
        return recovery_lead(self.slack, self.recovery_target)

    @property
    def problem_lead(self) -> int | None:
        """The attempt of the (6.15) chain a recovery solve runs first (``None``: none)."""
        return recovery_lead(self.problem, self.recovery_target)

    def _answered_by_lead(self, sol: Solution) -> bool:
        """Whether a converged (6.15) was answered by the solver of the recovery attempt
        (:attr:`problem_lead`), here as a retry of an ordinary step. The next (6.15) then
        starts from the candidate (6.14), as after a recovery solve: from the
        interior-point primal–dual point the first SQP attempt stops after one QP that
        costs up to 1.4 s under load (lane change, seed 9, steps 99–101; docs/vehicles.md,
        "session 13: Algorithm 6.4's worst steps"). The emitted C decides the same from
        the solver that answered (``bal/problem.c``'s ``which``)."""
        k = self.problem_lead
        if k is None or not sol.success:
            return False
        name = sol.raw.get("function")
        return name is not None and name == self.problem._retry_solvers()[k].name()

    def _duals_ok(self) -> bool:
        """Whether (6.15) is a CasADi problem (whose ``solve`` takes ``duals_from``)."""
        return getattr(self.problem, "backend", None) == "casadi"

    def recovering(self) -> bool:
        """Whether the (6.15) of this step is a recovery solve: no converged (6.15) yet to
        start from (its first solve, from the candidate)."""
        return self._last is None

    def step(self, x: np.ndarray, u_p: np.ndarray) -> tuple[np.ndarray, StepInfo]:
        """One step of Algorithm 6.4 (module docstring); never raises for runtime data."""
        where = "Algorithm 6.4 (MultiobjectivePCBFController.step: "
        u_p, replaced = finite_proposal(u_p, self.system.nu, where + "u_p)")
        x = finite_state(x, self.system.nx, where + "x)")
        if x is None:
            return projected_proposal(u_p, self.U)
        u, info = self._step(x, u_p)
        return u, note_proposal(info, replaced)

    def _step(self, x: np.ndarray, u_p: np.ndarray) -> tuple[np.ndarray, StepInfo]:
        nu = self.system.nu
        info = StepInfo()
        if self.candidate is None:                      # initialization from (5.15)
            s0 = self._h_r(x, lead=self.slack_lead)     # a recovery step: no candidate
            info.solve_time += s0.solve_time
            if not s0.success:
                info.status, info.fallback = f"init_{outcome(s0)}", "projected_proposal"
                return project(u_p, self.U), info
            note_solve(info, "slack", s0.status)
            xi0, xi0_N = tube_polished(self._tube, s0, self.X_E, self.h_f, self.deltas)
            self.candidate = Candidate(np.asarray(s0["z"], dtype=float),
                                       np.asarray(s0["v"], dtype=float).reshape(nu, -1),
                                       xi0, xi0_N)
            self.h_prev = self.h_tilde(xi0, xi0_N)
            if self.record_h_r:
                info.values["h_r"] = self.h_prev
        elif self.record_h_r:
            info.values["h_r"] = self._record_h_r(x, info)
        c = self.candidate
        h_cand = self.h_tilde(c.xi, c.xi_N)
        bound = decrease_bound(h_cand, float(self.h_prev), self.rho)
        bound += self.bound_tol * max(1.0, abs(bound))
        info.values.update({"h_cand": h_cand, "bound": bound})
        # from the candidate before the first converged (6.15) and after a recovery solve
        # until one converges (the interior-point point stops the SQP: docs/vehicles.md),
        # with zero multipliers; on ordinary steps from the previous (6.15), or with
        # candidate_duals from the candidate with the previous (6.15)'s multipliers
        warm = self._candidate_start(c)
        extra: dict = {}
        if self._last is not None and not self._recovered:
            if self.candidate_duals and self._duals_ok():
                extra["duals_from"] = self._last
            else:
                if self.candidate_second and self._duals_ok():
                    extra.update(second_start=warm, second_duals=self._last)
                warm = self._last
        lead = self.problem_lead if self.recovering() else None
        if lead is not None:
            extra["lead"] = lead
        sol = self.problem.solve({"x0": x, "u_p": u_p, "bound": bound}, warm_start=warm,
                                 **extra)
        # from the candidate again until a (6.15) converges after the recovery solve (the
        # C's warm start holds the candidate start then, not the interior-point point)
        self._recovered = lead is not None or (self._recovered and not sol.success) \
            or self._answered_by_lead(sol)
        info.solve_time += sol.solve_time
        info.solutions["problem"] = sol
        accepted = None
        if sol.success:
            self._last = sol
            accepted = self._meets_decrease(sol, bound, info)
        if accepted is not None:
            z, v, xi, xi_N = accepted
            note_solve(info, "problem", sol.status)   # optimal_inaccurate: flagged only
            info.status = "ok"
        elif sol.success:
            z, v, xi, xi_N = c.z, c.v, c.xi, c.xi_N
            info.status, info.fallback = "problem_above_bound", "warm_start"
        else:
            z, v, xi, xi_N = c.z, c.v, c.xi, c.xi_N
            info.status, info.fallback = f"problem_{outcome(sol)}", "warm_start"
        self.h_prev = self.h_tilde(xi, xi_N)
        info.values["h_tilde"] = self.h_prev
        self.candidate = self._make_candidate(z, v, xi)
        u = v[:, 0] + self.error.kappa(x - z[:, 0])
        return u, info

    def _meets_decrease(self, sol: Solution, bound: float, info: StepInfo
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
        """``(z, v, ξ, ξ_N)`` of a converged (6.15) whose trajectory meets (6.15g) with its
        minimal (polished) slacks, ``h̃ <= bound + DECREASE_TOL·max(1, |bound|)``; else
        ``None`` (the value is kept as ``values["h_tilde_rejected"]``). The solver meets
        each row and bound only within its primal tolerance, and ``α_f`` multiplies the
        error of ``ξ_N``: on the lane change (C, seeds 42 and 43) the chain's last attempt,
        interior point, returned ``ξ_N = −3.6e-12``, which freed ``α_f·3.6e-12 = 3.6e-6`` of the
        bound for the other slacks; that plan is no feasible point of (6.15) and ``h̃``
        rose by 3.6e-6 (docs/vehicles.md, "session 12"). Theorem 6.15 needs a feasible
        point; the candidate (6.14) is one, so the step falls back to it."""
        nu = self.system.nu
        xi, xi_N = tube_polished(self._tube, sol, self.X_E, self.h_f, self.deltas)
        h = self.h_tilde(xi, xi_N)
        if not h <= bound + DECREASE_TOL * max(1.0, abs(bound)):
            info.values["h_tilde_rejected"] = h
            return None
        return (np.asarray(sol["z"], dtype=float),
                np.asarray(sol["v"], dtype=float).reshape(nu, -1), xi, xi_N)

    def deployment_spec(self) -> MultiobjectiveDeployment:
        """Algorithm 6.4 for :func:`balustrade.codegen.emit_multiobjective` (one C call per
        step), also a :class:`~balustrade.control.deploy.ProblemsDeployment` of (5.15) and
        (6.15) for :func:`balustrade.codegen.emit_problems`."""
        return MultiobjectiveDeployment(
            {"slack": self.slack, "problem": self.problem},
            "Algorithm 6.4, the multiobjective robust PCBF controller",
            system=self.system, X_E=self.X_E, U=self.U, U_E=self.U_E, h_f=self.h_f,
            pi_f=self.pi_f, K=self.error.K if self.error.kappa_fn is None else None,
            deltas=self.deltas, alpha_f=self.alpha_f, rho=self.rho,
            bound_tol=self.bound_tol, record_h_r=self.record_h_r,
            recovery_target=self.recovery_target, candidate_duals=self.candidate_duals,
            candidate_second=self.candidate_second)
