"""The status codes of the emitted C, defined once: the ``#define`` lines of the generated
config headers (:mod:`~balustrade.codegen.cfiles`; the static C in ``codegen/c/`` only uses
the macro names), the manifests written by :mod:`~balustrade.codegen.emit` and the Python
names read by :mod:`~balustrade.codegen.runtime` are all generated from these tables.

Eight families:

* :data:`SOLVE` — return value of ``<problem>_solve`` (one problem, e.g. (2.24));
* :data:`PCBF` — return value of the PCBF step (2.24)+(2.23): which input it applied;
* :data:`APPROX` — return value of the Algorithm 7.5 step (7.5)+(7.6);
* :data:`GRID` — return value of the Algorithm 8.7 step (grid filter, no solver);
* :data:`ROBUST` — return value of the Algorithm 5.2 step (5.15)+(5.16);
* :data:`MULTIOBJ` — return value of the Algorithm 6.4 step ((5.15) once, then (6.15));
* :data:`RAPSF` — return value of the Algorithm 4.1 step ((4.5), stored plan, backup);
* :data:`MO_LYAP` — return value of the Algorithm 6.3 step ((6.3) once, then (6.10)).

A problem emitted from a target with an iteration budget (real-time mode, issue #14 §5:
``Target.with_budget``, the ``"real-time"`` preset) reports a solve stopped by it as
``BAL_TRUNCATED`` (:data:`SOLVE`), the C twin of a solve the backend reports as truncated
(``Solution.truncated``); the PCBF step applies the truncation policy of
:mod:`balustrade.control.pcbf` to it, and the runtime reports it with the word
``"truncated"`` as ``StepInfo`` does in Python.

Each family has a *bad input* code: a parameter or state that is NaN or inf is refused
before any solver runs (NaN compares false, so a residual test would pass it as
converged); the steps then apply the proposal, NaN entries replaced by 0, clipped to ``U``
(the fallback of :func:`balustrade.control.fallbacks.projected_proposal`). A non-finite
*proposal* with a finite state is not refused: its non-finite entries are replaced by 0
and the step runs as usual, so the applied input is still the safety filter's
(:func:`balustrade.control.fallbacks.finite_proposal`); the step's
``<name>_proposal_replaced`` says how many entries were replaced.
"""

from __future__ import annotations

from typing import NamedTuple


class Status(NamedTuple):
    """One status code: C macro, value, Python name, fallback applied (steps), C comment."""

    macro: str
    code: int
    name: str
    fallback: str | None
    doc: str


#: ``<problem>_solve``: ``name`` is the status string of :class:`~balustrade.codegen.CProblem`.
SOLVE: tuple[Status, ...] = (
    Status("BAL_OK", 0, "ok", None,
           "converged: primal and dual residuals below the tolerances"),
    Status("BAL_NOT_CONVERGED", 1, "not_converged", None,
           "stopped without convergence (iteration limit, infeasible)"),
    Status("BAL_EVAL_ERROR", 2, "eval_error", None,
           "CasADi reported an evaluation error, or not initialized"),
    Status("BAL_NONFINITE", 3, "nonfinite", None, "the solution contains NaN or inf"),
    Status("BAL_FEASIBLE", 4, "feasible", None,
           "no attempt converged (all retries done), but the last one is primal feasible up "
           "to the problem's acceptance tolerance (e.g. the SQP stalled on a vanishing "
           "step): safe to apply, possibly suboptimal"),
    Status("BAL_BAD_INPUT", 5, "bad_input", None,
           "a parameter is NaN or inf (or p is NULL): nothing was solved, the solution "
           "and value are NaN"),
    Status("BAL_TRUNCATED", 6, "truncated", None,
           "stopped by the problem's iteration budget (P_BUDGET > 0, real-time mode) "
           "before converging: not retried, never optimal; its iterate, value and primal "
           "residual (residuals[0]) are in the work struct, and a step applies it only when "
           "that residual is <= P_TRUNC_TOL"),
    Status("BAL_NOT_RUN", -1, "not_run", None, "the solve was not attempted"),
)

#: The PCBF step (2.24)+(2.23): ``fallback`` is the StepInfo fallback of
#: :class:`~balustrade.control.pcbf.PCBFSafetyFilter`.
PCBF: tuple[Status, ...] = (
    Status("BAL_PCBF_OK", 0, "ok", None, "u*_{0|k} of the filter (2.23)"),
    Status("BAL_PCBF_SLACK_SOLUTION", 1, "slack_solution", "slack_solution",
           "(2.23) failed: u_{0|k} of (2.24)"),
    Status("BAL_PCBF_SHIFTED_PLAN", 2, "shifted_plan", "shifted_plan",
           "(2.24) failed: the next input of the last plan"),
    Status("BAL_PCBF_PROJECTED", 3, "projected_proposal", "projected_proposal",
           "(2.24) failed and no plan is left: u_p clipped to U"),
    Status("BAL_PCBF_BAD_INPUT", 4, "bad_input", "projected_proposal",
           "x is NaN or inf (or a pointer is NULL): nothing solved, u_p (NaN -> 0) "
           "clipped to U"),
    Status("BAL_PCBF_FEASIBLE_SLACK", 5, "feasible_slack", "feasible_slack",
           "(2.24) only feasible (not converged, cost > 0: an upper bound on h_PB, h_out "
           "NAN) and no plan left: (2.23) on its slacks (or its u_{0|k} if (2.23) fails)"),
)

#: The Algorithm 7.5 step: ``fallback`` as in
#: :class:`~balustrade.control.approximate.ApproximatePCBFFilter`.
APPROX: tuple[Status, ...] = (
    Status("BAL_APPROX_OK", 0, "ok", None, "the minimizer of the filter (7.5)"),
    Status("BAL_APPROX_CERTIFIED", 1, "certified", None,
           "u_p certified by one evaluation (line 4)"),
    Status("BAL_APPROX_MAX_DECREASE", 2, "filter_failed", "max_decrease_solution",
           "(7.5) failed or left U: the (7.6) minimizer"),
    Status("BAL_APPROX_BAD_INPUT", 3, "bad_input", "projected_proposal",
           "x is NaN or inf (or a pointer is NULL): u_p (NaN -> 0) clipped to U"),
    Status("BAL_APPROX_GRID_MINIMIZER", 4, "max_decrease_failed", "grid_minimizer",
           "(7.6) found nothing finite: the best screened candidate"),
    Status("BAL_APPROX_PROPOSAL_FEASIBLE", 5, "proposal_feasible", None,
           "u_p meets the decrease of (7.5): its minimizer (exact shortcut)"),
    Status("BAL_APPROX_FILTER_FEASIBLE", 6, "filter_feasible", None,
           "(7.5) only feasible (not converged): a safe input in U meeting the decrease, "
           "possibly not the closest to u_p"),
)

#: The Algorithm 8.7 step: ``name`` and ``fallback`` are the StepInfo status and fallback of
#: :class:`~balustrade.control.approximate.GridPCBFFilter`.
GRID: tuple[Status, ...] = (
    Status("BAL_GRID_OK", 0, "ok", None,
           "the admissible candidate closest to u_p (input-range-scaled norm)"),
    Status("BAL_GRID_NO_DECREASE", 1, "no_decreasing_candidate", "grid_minimizer",
           "no candidate meets h^(f(x, u)) <= rho h^(x): the grid minimizer"),
    Status("BAL_GRID_BAD_INPUT", 2, "non_finite_state", "previous_input",
           "x is NaN or inf (or a pointer is NULL): the last applied input, unchanged"),
)


#: The Algorithm 5.2 step (5.15)+(5.16): ``fallback`` as in
#: :class:`~balustrade.control.robust.RobustPCBFSafetyFilter` (a solve counts as a success
#: only when it converged, ``BAL_OK``: the backend's ``feasible`` is a failure there).
ROBUST: tuple[Status, ...] = (
    Status("BAL_ROBUST_OK", 0, "ok", None, "v*_0 + K(x - z*_0) of the filter (5.16)"),
    Status("BAL_ROBUST_SLACK_SOLUTION", 1, "slack_solution", "slack_solution",
           "(5.16) failed: v_0 + K(x - z_0) of the (5.15) optimizer"),
    Status("BAL_ROBUST_CANDIDATE", 2, "candidate", "candidate",
           "(5.15) failed: v~_0 + K(x - z~_0) of the last candidate (5.17), shifted again"),
    Status("BAL_ROBUST_PROJECTED", 3, "projected_proposal", "projected_proposal",
           "(5.15) failed and no candidate: u_p clipped to U"),
    Status("BAL_ROBUST_BAD_INPUT", 4, "bad_input", "projected_proposal",
           "x is NaN or inf (or a pointer is NULL): nothing solved, u_p (NaN -> 0) "
           "clipped to U"),
    Status("BAL_ROBUST_ABOVE_CANDIDATE", 5, "above_candidate", "candidate",
           "(5.15) converged above the candidate's h~ (a worse local solution): as "
           "BAL_ROBUST_CANDIDATE"),
)


#: The Algorithm 6.4 step: ``fallback`` as in
#: :class:`~balustrade.control.multiobjective.MultiobjectivePCBFController` (only
#: ``BAL_OK`` is a success, as only ``optimal`` is in Python).
MULTIOBJ: tuple[Status, ...] = (
    Status("BAL_MULTIOBJ_OK", 0, "ok", None, "v*_0 + K(x - z*_0) of (6.15)"),
    Status("BAL_MULTIOBJ_WARM_START", 1, "warm_start", "warm_start",
           "(6.15) failed: v~_0 + K(x - z~_0) of the candidate (6.14)"),
    Status("BAL_MULTIOBJ_INIT_FAILED", 2, "init_failed", "projected_proposal",
           "no candidate and (5.15) failed: u_p clipped to U"),
    Status("BAL_MULTIOBJ_BAD_INPUT", 3, "bad_input", "projected_proposal",
           "x is NaN or inf (or a pointer is NULL): nothing solved, u_p (NaN -> 0) "
           "clipped to U"),
    Status("BAL_MULTIOBJ_ABOVE_BOUND", 4, "above_bound", "warm_start",
           "(6.15) converged, but its polished slacks' h~ is above the bound of (6.15g) "
           "(the returned point is not feasible for (6.15)): as BAL_MULTIOBJ_WARM_START"),
)


#: The Algorithm 4.1 step: ``fallback`` as in :class:`~balustrade.control.rapsf.RAPSF`
#: (only ``BAL_OK`` is a success, as only ``optimal`` is in Python).
RAPSF: tuple[Status, ...] = (
    Status("BAL_RAPSF_OK", 0, "ok", None, "K x + v*_0 of (4.5); the plan is stored"),
    Status("BAL_RAPSF_STORED_PLAN", 1, "stored_plan", "stored_plan",
           "(4.5) failed: K x + v*_{k_inf} of the stored plan (k_inf <= N - 1)"),
    Status("BAL_RAPSF_BACKUP", 2, "backup", "backup",
           "(4.5) failed and no plan left: the backup policy K x"),
    Status("BAL_RAPSF_FALSIFIED", 3, "model_falsified", "backup",
           "the estimator excluded every model: the backup policy K x, nothing solved"),
    Status("BAL_RAPSF_BAD_INPUT", 4, "bad_input", "backup",
           "x is NaN or inf (or a pointer is NULL): nothing solved, K x with NaN -> 0"),
    Status("BAL_RAPSF_SHRUNK_HORIZON", 5, "shrunk_horizon", "shrunk_horizon",
           "(4.5) failed: K x + v*_0 of (4.5) with the horizon N - k_inf (Remark 4.6)"),
)


#: The Algorithm 6.3 step: ``fallback`` as in
#: :class:`~balustrade.control.multiobjective.MultiobjectiveLyapunovController` (only
#: ``BAL_OK`` is a success, as only ``optimal`` is in Python).
MO_LYAP: tuple[Status, ...] = (
    Status("BAL_MO_LYAP_OK", 0, "ok", None, "v*_0 of (6.10)"),
    Status("BAL_MO_LYAP_WARM_START", 1, "warm_start", "warm_start",
           "(6.10) failed: u~_0 of the warm start (6.6)/(6.7), feasible for (6.3b-h)"),
    Status("BAL_MO_LYAP_INIT_FAILED", 2, "init_failed", "projected_proposal",
           "first step and (6.3) without (6.3h) failed: u_p clipped to U"),
    Status("BAL_MO_LYAP_BAD_INPUT", 3, "bad_input", "projected_proposal",
           "x is NaN or inf (or a pointer is NULL): nothing solved, u_p (NaN -> 0) "
           "clipped to U"),
)


#: every family (the static C may use the macros of any of them)
FAMILIES: tuple[tuple[Status, ...], ...] = (SOLVE, PCBF, APPROX, GRID, ROBUST, MULTIOBJ,
                                            RAPSF, MO_LYAP)


def by_code(family: tuple[Status, ...]) -> dict[int, Status]:
    """``{code: Status}`` of a family."""
    return {s.code: s for s in family}


def code_of(family: tuple[Status, ...], name: str) -> int:
    """The code of the status called ``name`` in ``family``."""
    return next(s.code for s in family if s.name == name)


def c_defines(family: tuple[Status, ...]) -> str:
    """``#define`` lines of a family for the generated header (negative codes bracketed)."""
    lines = []
    for s in family:
        value = f"({s.code})" if s.code < 0 else str(s.code)
        lines.append(f"#define {s.macro} {value}  /* {s.doc} */")
    return "\n".join(lines) + "\n"


def manifest(family: tuple[Status, ...]) -> dict[str, int]:
    """``{name: code}`` of a family, as written to the manifest."""
    return {s.name: s.code for s in family}
