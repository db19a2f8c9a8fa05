"""Lowering of an :class:`~balustrade.dsl.ocp.OCP` to a parametric CasADi NLP.

Compiled once (``nlpsol``), solved many times with new parameter values and primal-dual
warm starts (DESIGN.md principle 2). The lowering is the chain
:data:`balustrade.backends.passes.CASADI_CHAIN`: the epigraph pass
(:mod:`~balustrade.backends.passes.epigraph`) turns non-smooth cost terms into epigraph
variables ``t`` (cost ``c·t``) added to the one :class:`~balustrade.dsl.layout.Layout`,
every form exact:

* ``‖a‖₁``: ``Σ a`` when ``a`` are nonnegative variables (the slacks ``ξ >= 0`` of (2.24),
  (5.15)), else ``−t <= a <= t`` with cost ``Σ t``;
* ``‖a‖∞``: ``a_j <= t`` for nonnegative variables (``‖ξ‖∞ = max_j ξ_j``), else
  ``−t <= a_j <= t``;
* ``max_j a_j``: ``a_j <= t``;
* ``‖a‖₂``: the perspective (quadratic-over-linear) form ``aᵀa / max(t, ε) − t <= 0`` with
  ``t >= 0``, plus the valid cuts ``a_j <= t`` (nonnegative variables) or ``−t <= a_j <= t``
  (``‖a‖∞ <= ‖a‖₂``), ``ε = 1e-12``.

Why this 2-norm form (issue #12). The textbook smooth form ``aᵀa − t² <= 0`` has a zero
gradient at the apex ``a = 0, t = 0``, which is where a slack column of (2.24) sits whenever
its constraints are inactive or just active. There no KKT point exists when a state row is
active with a positive multiplier ``μ`` (the subgradient ``μ ∈ ∂‖·‖₂(0)`` cannot be produced
by a vanishing constraint gradient): IPOPT's multipliers diverge and it ends in
``Infeasible_Problem_Detected``/restoration failure on a problem that is always feasible, and
sqpmethod's QP linearization at the apex loses the coupling of ``a`` and ``t``; the backend
then returned a far-off primal-feasible point (``h_PB ≈ 570`` instead of ``0.041``). The
perspective constraint describes the same cone (for ``t >= ε`` exactly; for ``0 <= t < ε``
it allows ``‖a‖₂ <= √(tε)``, so ``t`` under-counts ``‖a‖₂`` by at most ``ε/4``), is convex
for ``t > 0``, positively homogeneous, and its gradient ``(2a/t, −1 − ‖a‖²/t²)`` never
vanishes: its limiting gradients at the apex, ``λ(2d, −1 − ‖d‖²)`` with ``‖d‖ <= 1``, span
the cone's normal cone, so the KKT multipliers stay finite. The cuts are implied by the cone
(exactness is untouched) and give the QP subproblems of sqpmethod the apex coupling the
curved row lacks there. Measured on the pendulum grid and a nonlinear lane-keeping problem
(``benchmarks/bench_norms.py``): no wrong values, and 2–4× fewer IPOPT iterations than the
``aᵀa <= t²`` form. Alternatives rejected: ``√(aᵀa + ε²) − ε`` (inexact by up to ``ε`` and
ill-conditioned), the direction lifting ``a = t·d, ‖d‖ <= 1`` (satisfies LICQ but is
bilinear: ``a = 0, t = 0, d = 0`` is a spurious local minimum), the cuts alone on the old
form (still no KKT point: IPOPT failed on 57/81 pendulum states).

The reported ``Solution.objective`` is always the declared cost evaluated at the returned
primal point (never the epigraph value), so it is the exact value of that point.
"""

from __future__ import annotations

import copy
import dataclasses
import re
import time

import casadi as ca
import numpy as np

from balustrade.backends.passes import CASADI_CHAIN, run_chain
from balustrade.backends.passes.casadi_nlp import as_dm, compact_nlp
from balustrade.backends.passes.epigraph import EpigraphInverse
from balustrade.backends.passes.stage_order import (
    StagedNLP,
    StageInverse,
    StructureError,
    stage_order,
    staged_compact,
)
from balustrade.backends.solution import Solution, Status
from balustrade.backends.targets import Budget
from balustrade.dsl.costs import TermKind
from balustrade.dsl.ocp import OCP
from balustrade.errors import SolverError

DEFAULT_OPTIONS: dict[str, dict] = {
    "ipopt": {"ipopt.print_level": 0, "ipopt.sb": "yes", "print_time": False,
              "ipopt.tol": 1e-10, "ipopt.acceptable_tol": 1e-8, "ipopt.max_iter": 500,
              # exact bounds and complementarity: slacks weighted by alpha_f = 1e6 would
              # otherwise sit ~1e-12 inside their bounds, i.e. ~1e-6 in h_PB
              "ipopt.bound_relax_factor": 0.0, "ipopt.compl_inf_tol": 1e-12},
    "sqpmethod": {"qpsol": "qrqp", "print_time": False, "print_header": False,
                  "print_iteration": False, "print_status": False,
                  "max_iter": 100, "tol_pr": 1e-9, "tol_du": 1e-6,
                  # qrqp needs a positive definite Hessian (the Lagrangian's is singular
                  # for LP-like slack problems and input-only filter costs). Eigenvalue
                  # clipping, not "regularize"/"none": with those, CasADi 3.8's qrqp
                  # corrupts the heap on small problems (docs/design-notes.md).
                  "convexify_strategy": "eigen-clip", "error_on_fail": False},
    # fatrop: the problem is compiled in stage order with manual structure options
    # (stage_order.py, casadi_backend.with_structure)
    "fatrop": {"print_time": False, "fatrop": {"print_level": 0, "max_iter": 300}},
}

#: ``qpsol_options`` added for sqpmethod's QP solver, per plugin (each plugin accepts only
#: its own options: qrqp's ``print_header`` makes OSQP refuse to build); other plugins get
#: only the user's ``qpsol_options``
QPSOL_DEFAULTS: dict[str, dict] = {
    # max_iter 100 (qrqp's default: 1000): on degenerate active sets qrqp cycles, adding
    # and dropping the same row ("Enforced ubz to reduce |du|" / "Dropped ubz for
    # regularity") until max_iter, 30-60 ms per QP on the cart-pole PCBF (N = 20); the
    # QPs that converge need < 60 iterations there and on the pendulum. Measured on the
    # cart-pole closed loop (40 steps, interleaved, CPU time, under load): median step
    # 1455 -> 273 ms, worst 3335 -> 562 ms, failures 0 -> 0, inputs equal to 2.5e-10.
    # min_lam (qrqp: "smallest multiplier treated as inactive", default 0): together with
    # the objective scaling of objective_scale it takes the emittable chain from 72 to 2
    # failures of (5.15) in 200 states of the 2-D example (46 with the scaling alone;
    # tests/test_sqp_convergence.py). 1e-14, not larger: with 1e-8 or 1e-6 the pendulum
    # (2.24) failed on 3 of the 1000 states of test_codegen (0 with 1e-14 and 1e-18)
    "qrqp": {"print_iter": False, "print_header": False, "print_info": False,
             "error_on_fail": False, "max_iter": 100, "min_lam": 1e-14},
    "hpipm": {"hpipm": {"iter_max": 200, "res_g_max": 1e-10, "res_b_max": 1e-10,
                        "res_d_max": 1e-10, "res_m_max": 1e-10},
              "error_on_fail": False},
    "osqp": {"osqp": {"verbose": False, "eps_abs": 1e-9, "eps_rel": 1e-9, "max_iter": 20000,
                      "polish": True}, "error_on_fail": False},
}


def solver_options(solver: str, options: dict | None = None) -> dict:
    """The options :class:`CasadiCompiled` passes to ``nlpsol(…, solver, …)``: the defaults
    of :data:`DEFAULT_OPTIONS` updated by ``options``; for ``sqpmethod`` the
    ``qpsol_options`` are the chosen ``qpsol``'s defaults (:data:`QPSOL_DEFAULTS`)
    updated by the user's (nested dictionaries such as ``{"osqp": {…}}`` merged).

    Unknown options are reported when the solver is built (:func:`_nlpsol`)."""
    opts = {**DEFAULT_OPTIONS.get(solver, {}), **(options or {})}
    if solver == "sqpmethod":
        user_qp = dict((options or {}).get("qpsol_options", {}))
        qp = {k: dict(v) if isinstance(v, dict) else v
              for k, v in QPSOL_DEFAULTS.get(opts.get("qpsol", "qrqp"), {}).items()}
        for k, v in user_qp.items():
            qp[k] = {**qp[k], **v} if isinstance(v, dict) and isinstance(qp.get(k), dict) \
                else v
        opts["qpsol_options"] = qp
    return opts


#: :func:`objective_scale` and :func:`row_scale` scale an sqpmethod objective or row whose
#: gradient is larger than this (IPOPT's ``nlp_scaling_max_gradient``). Not 1: scaling
#: ``1e6 ξ_N + Σ ξ`` to gradient 1 puts the ``Σ ξ`` part (1e-6) below qrqp's absolute dual
#: tolerance, and sqpmethod then reported "optimal" after one iteration at a point 30 %
#: worse (the pendulum (2.24), tests/test_casadi_backend.py). Termination tolerances are
#: those of the scaled problem, as in IPOPT.
OBJECTIVE_MAX_GRADIENT = 100.0


def objective_scale(nlp: dict, x0: np.ndarray, solver: str) -> float:
    """The factor ``s <= 1`` by which the objective handed to ``sqpmethod`` is multiplied:
    ``OBJECTIVE_MAX_GRADIENT / max|∇f(x0, p = 0)|`` when that gradient is larger, else 1
    (other solvers: 1; IPOPT scales by itself, ``nlp_scaling_method`` gradient-based).

    Why (issue #14 §3): the slack problems (5.15)/(6.15) weigh ``ξ_N`` by ``α_f = 1e6``, so
    the multipliers of the dynamics and tube rows reach 1e8 while the rows are O(1). CasADi's
    sqpmethod has no NLP scaling, and qrqp's absolute tolerances (1e-8) then cannot tell an
    active from an inactive row: it cycles (``Enforced ubz to reduce |du|`` / ``Dropped ubz
    for regularity``) to its ``max_iter``, returns a point violating ``ξ >= 0``, and the SQP
    stops with ``Search_Direction_Becomes_Too_Small``. On the unstable 2-D example (N = 10)
    the emittable chain alone failed (5.15) on 72 of 200 random states; with this scaling
    and qrqp's ``min_lam`` (:data:`QPSOL_DEFAULTS`) on 2 (``tests/test_sqp_convergence.py``).
    The minimizer is unchanged; the multipliers are divided by ``s`` when reported.
    ``x0`` is the layout's initial point; a non-finite gradient there gives 1."""
    if solver != "sqpmethod":
        return 1.0
    grad = ca.Function("grad_f", [nlp["x"], nlp["p"]], [ca.gradient(nlp["f"], nlp["x"])])
    g = np.abs(np.asarray(grad(x0, np.zeros(nlp["p"].numel())), dtype=float))
    top = float(np.max(g, initial=0.0))
    if not np.isfinite(top) or top <= OBJECTIVE_MAX_GRADIENT:
        return 1.0
    return OBJECTIVE_MAX_GRADIENT / top


def row_scale(nlp: dict, x0: np.ndarray, solver: str) -> np.ndarray | None:
    """Per-row factors ``s_i <= 1`` for ``sqpmethod``: ``OBJECTIVE_MAX_GRADIENT /
    max|∇g_i(x0, p = 0)|`` for the rows whose gradient there is larger, else 1 (IPOPT's
    gradient-based rule, which sqpmethod lacks); ``None`` when no row is scaled.

    Why: (6.15g) ``α_f ξ_N + Σ 1ᵀξ_i <= bound`` has the coefficient ``α_f = 1e6``; unscaled,
    the emittable chain alone failed (6.15) on every one of 198 random states of the 2-D
    example (``Search_Direction_Becomes_Too_Small``), with it on 36. Rows and their bounds
    are scaled together (the feasible set is unchanged); a row multiplier is
    ``λ_i = λ̃_i s_i / s_f``."""
    if solver != "sqpmethod" or nlp["g"].numel() == 0:
        return None
    jac = ca.Function("jac_g", [nlp["x"], nlp["p"]], [ca.jacobian(nlp["g"], nlp["x"])])
    J = np.abs(np.asarray(ca.densify(jac(x0, np.zeros(nlp["p"].numel()))), dtype=float))
    top = np.max(J, axis=1, initial=0.0)
    big = np.isfinite(top) & (top > OBJECTIVE_MAX_GRADIENT)
    if not np.any(big):
        return None
    scale = np.ones(top.size)
    scale[big] = OBJECTIVE_MAX_GRADIENT / top[big]
    return scale


def _refuse_fatrop_hang(ocp: OCP) -> None:
    """fatrop (``structured-ip``) is refused on a cost with a 2-norm term: there a fatrop
    solve can hang, and nothing bounds it.

    Cause (CasADi 3.8.2, fatrop 1.1.8; docs/engines.md "Why fatrop hung"): fatrop's search
    direction is computed in a loop that raises the primal regularization ``δ_w`` (×8 per
    try) for as long as the linear solver reports an indefinite reduced Hessian, *without an
    upper bound* (IPOPT gives up at ``δ_w > 1e40``). Once ``δ_w`` overflows to ``inf`` the
    system is NaN and reported indefinite forever: one iteration never ends, so
    ``max_iter`` (checked between iterations) cannot stop it, and fatrop has no time limit.
    Seen on the nonlinear lane-keeping (2.24) with the 2-norm slack cost (11 115 solves of
    the same iteration's system in 15 s, every one "indefinite"): CasADi hands variable
    bounds to fatrop as inequality rows with slacks, so fatrop's iterates leave ``t >= 0``
    and the perspective row ``aᵀa / max(t, ε) − t`` (``ε = 1e-12``) puts ``2/ε`` into the
    Hessian. The 1-norm and ∞-norm forms (linear rows) did not hang on the bicycle (5.15),
    the lane-keeping (2.24) or the cart-pole (2.24) (tests/test_structured.py)."""
    for term in ocp.cost.terms:
        if term.kind == TermKind.NORM2:
            raise StructureError(
                f"{ocp.name}: the cost has a 2-norm term ({term.label or 'unnamed'}); the "
                "fatrop target ('structured-ip') is refused there: its perspective row can "
                "make a fatrop solve loop forever (an unbounded regularization loop inside "
                "one iteration, no iteration or time limit applies); use 'long-horizon' or "
                "'exact', or a 1-/inf-norm slack cost")


def needs_stage_order(solver: str, opts: dict) -> bool:
    """Whether ``solver`` with ``opts`` exploits stage structure, so the problem is compiled
    in stage order (:mod:`~balustrade.backends.passes.stage_order`): ``fatrop``, and
    ``sqpmethod`` with ``qpsol`` ``hpipm``."""
    return solver == "fatrop" or (solver == "sqpmethod" and opts.get("qpsol") == "hpipm")


def with_structure(solver: str, opts: dict, staged: StagedNLP) -> dict:
    """``opts`` with the per-stage sizes of ``staged``: fatrop's own options, or HPIPM's in
    sqpmethod's ``qpsol_options``."""
    if solver == "fatrop":
        return {**opts, **staged.structure("fatrop")}
    qp = dict(opts.get("qpsol_options", {}))
    return {**opts, "qpsol_options": {**qp, **staged.structure("hpipm")}}


def _nlpsol(name: str, solver: str, nlp: dict, opts: dict) -> ca.Function:
    """``ca.nlpsol`` with CasADi's construction errors as :class:`SolverError` naming the
    solver and the option: an unknown option of the NLP solver, of IPOPT
    (``ipopt.<name>``) or of sqpmethod's QP solver (``qpsol_options``), or a bad value."""
    try:
        return ca.nlpsol(name, solver, nlp, opts)
    except RuntimeError as exc:
        raise SolverError(_build_error(name, solver, opts, str(exc))) from exc


def _build_error(name: str, solver: str, opts: dict, text: str) -> str:
    lines = [re.sub(r"^.*?\.(?:cpp|hpp):\d+:\s*", "", ln.strip())
             for ln in text.splitlines() if ln.strip()]
    lines = [ln for ln in lines if not ln.startswith("Error calling")] or [text]
    hints = re.findall(r'^> "([^"]+)"', text, flags=re.M)
    unknown = re.search(r"(?:Unknown option|No such IPOPT option):\s*(\S+)", text)
    if not unknown:
        return f"{name}: CasADi could not build solver {solver!r}: {lines[0]}"
    opt = unknown.group(1)
    if "IPOPT" in unknown.group(0):
        where = f"IPOPT option 'ipopt.{opt}' (solver {solver!r})"
    elif solver == "sqpmethod" and (opt in opts.get("qpsol_options", {}) or opt not in opts):
        where = (f"option {opt!r} in qpsol_options of sqpmethod's QP solver "
                 f"{opts.get('qpsol', 'qrqp')!r}")
    else:
        where = f"option {opt!r} for CasADi solver {solver!r}"
    return (f"{name}: unknown {where}"
            + (f"; did you mean {', '.join(repr(h) for h in hints[:3])}?" if hints else ""))


class CasadiCompiled:
    """A compiled CasADi problem: call :meth:`solve` with parameter values."""

    backend = "casadi"

    def __init__(self, ocp: OCP, solver: str = "ipopt", options: dict | None = None,
                 retries: list[tuple[str, dict]] | None = None):
        if not ca.has_nlpsol(solver):
            raise SolverError(f"{ocp.name}: unknown CasADi NLP solver {solver!r} "
                              "(try 'ipopt', 'sqpmethod' (with qrqp), 'fatrop')")
        self.ocp, self.solver_name = ocp, solver
        opts = solver_options(solver, options)
        #: which NLP the solver is built on (:data:`LOWERINGS`): a balustrade option,
        #: taken out of the solver's options
        lowering = opts.pop(LOWERING_OPTION, "expanded")
        #: the target is one the C emitters generate (``lowering: "as-emitted"``): its
        #: retries on another plugin stop as their emitted C does (:meth:`_retry_options`)
        self.as_emitted = lowering == AS_EMITTED
        if lowering == AS_EMITTED:  # the NLP the C emitters generate for this solver
            lowering = "expanded" if needs_stage_order(solver, opts) else "compact"
        self.lowering = _lowering(ocp.name, lowering)
        data, inverses = run_chain(CASADI_CHAIN, ocp)
        self._data = data
        #: how the epigraph pass maps a solver point back (user variables, declared cost)
        self.inverse: EpigraphInverse = inverses[0][1]
        #: the solver's decision vector: the user's variables, then the epigraph blocks
        self.layout = data.layout
        self.lbx, self.ubx, self.lbg, self.ubg = data.lbx, data.ubx, data.lbg, data.ubg
        self._x0 = self._x0_layout = data.x0
        self.block_slices: dict[str, slice] = data.block_rows
        self.n_g_user = data.n_g_user
        #: the stage-order inverse when the solver exploits stage structure (fatrop,
        #: sqpmethod + hpipm): the solver's vector is then the staged one (stage_order.py)
        self.stages: StageInverse | None = None
        if needs_stage_order(solver, opts):
            if solver == "fatrop":
                _refuse_fatrop_hang(ocp)
            if self.lowering != "expanded":
                raise SolverError(f"{ocp.name}: the {self.lowering!r} lowering is not "
                                  f"available for the stage-ordered solver {solver!r}")
            self._layout_bounds = (data.lbx, data.ubx)
            self._layout_data = data  # for the compact lowering of the C (staged_compact)
            staged, self.stages = stage_order(ocp, data, last_controls=solver == "fatrop")
            opts = with_structure(solver, opts, staged)
            self.lbx, self.ubx, self.lbg, self.ubg = (staged.lbx, staged.ubx, staged.lbg,
                                                      staged.ubg)
            self._x0 = staged.x0
            data = staged
            self._data = data
        # the factors the solver's objective and rows are multiplied by (objective_scale,
        # row_scale; sqpmethod with qrqp only): multipliers are mapped back on the way out,
        # warm starts stay in solver units, lbg/ubg/nlp are the scaled ones. Not with hpipm
        # ("structured-sqp"): there the scaled dual tolerance moved the initial-state
        # multiplier of the pendulum (2.24) by 0.3 % (test_structured)
        scaled = solver if opts.get("qpsol", "qrqp") == "qrqp" else "unscaled"
        self.objective_scale = objective_scale(data.nlp, data.x0, scaled)
        self.row_scale = row_scale(data.nlp, data.x0, scaled)
        if self.objective_scale != 1.0 or self.row_scale is not None:
            rs = np.ones(data.lbg.size) if self.row_scale is None else self.row_scale
            data = dataclasses.replace(
                data, nlp={**data.nlp, "f": data.nlp["f"] * self.objective_scale,
                           "g": data.nlp["g"] * ca.DM(rs)},
                lbg=data.lbg * rs, ubg=data.ubg * rs)
            self.lbg, self.ubg = data.lbg, data.ubg
        self._data = data  # what the lowerings (expanded, compact) are built from
        self.options = opts
        nlp, derivatives = self._lower(self.lowering)
        self.nlp = nlp
        #: derivative functions shared by every sqpmethod built on this NLP (first attempt,
        #: retries, the C of :mod:`balustrade.codegen`): see :func:`shared_derivatives`
        self.derivatives = derivatives
        self.solver = _nlpsol(ocp.name, solver, nlp, {**opts, **self.derivatives})
        #: cold-start attempts after a failed solve: (solver plugin, option overrides)
        self.retries = default_retries(solver, opts) if retries is None else list(retries)
        self._retry: list[ca.Function] | None = None
        self._g_function: ca.Function | None = None
        self._complementarity_fn: ca.Function | None = None
        self._dm = as_dm(data)
        self._lowered: dict[str, tuple[dict, dict]] = {
            self.lowering: (self.nlp, self.derivatives)}

    def lowered(self, lowering: str) -> tuple[dict, dict[str, ca.Function]]:
        """``(nlp, shared derivatives)`` of this problem in ``lowering`` (:data:`LOWERINGS`):
        the solver's own for :attr:`lowering`, else built once on first use (same
        variables, rows and values; the C emitters ask for ``"compact"``)."""
        if lowering not in self._lowered:
            if self.stages is not None:
                raise SolverError(f"{self.ocp.name}: the {lowering!r} lowering is not "
                                  f"available for the stage-ordered solver "
                                  f"{self.solver_name!r}")
            self._lowered[lowering] = self._lower(_lowering(self.ocp.name, lowering))
        return self._lowered[lowering]

    def staged_compact(self) -> tuple[dict, dict[str, dict[str, ca.Function]]]:
        """For a problem compiled in stage order: the compact lowering in stage order and
        the derivative functions per solver plugin (``nlpsol``'s ``cache`` option), built
        once (:func:`~balustrade.backends.passes.stage_order.staged_compact`; what the C
        emitters generate fatrop's and its IPOPT retry's code from). The Python solver
        keeps the expanded NLP; the values are the same."""
        if self.stages is None:
            raise SolverError(f"{self.ocp.name}: not compiled in stage order")
        if "staged_compact" not in self._lowered:
            self._lowered["staged_compact"] = staged_compact(
                compact_nlp(self._layout_data, self.ocp), self.stages)
        return self._lowered["staged_compact"]

    def _lower(self, lowering: str) -> tuple[dict, dict[str, ca.Function]]:
        if lowering == "expanded":
            nlp = self._data.nlp
            return nlp, shared_derivatives(nlp, self.solver_name, self.options)
        compact = compact_nlp(self._data, self.ocp)
        return compact.nlp, (compact.derivatives() if _shares_derivatives(
            self.solver_name, self.options) else {})

    @property
    def n_user(self) -> int:
        """Size of the user's part of the solver's decision vector (``layout.user_size``;
        kept for callers written before :class:`~balustrade.dsl.layout.Layout`)."""
        return self.layout.user_size

    def with_retries(self, retries: list[tuple[str, dict]]) -> CasadiCompiled:
        """A copy of this compiled problem (sharing its built solver) that runs ``retries``
        after a failed solve; this object is unchanged."""
        other = copy.copy(self)
        other.retries = [(name, dict(opts)) for name, opts in retries]
        other._retry = None
        if getattr(self, "target", None) is not None:
            other.target = self.target.with_retries(other.retries)
        return other

    def solve(self, params: dict[str, object] | None = None,
              warm_start: Solution | dict[str, object] | None = None,
              second_start: Solution | dict[str, object] | None = None,
              second_solver: int = 0,
              lead: int | None = None,
              duals_from: Solution | None = None,
              second_duals: Solution | None = None) -> Solution:
        """Solve with the given parameter values; ``warm_start`` is a previous
        :class:`Solution` (primal and dual) or a dict of variable values.

        ``duals_from`` (optional): a converged solution of this problem whose multipliers
        start the first attempt, the primal point coming from ``warm_start`` (Algorithm
        6.4's ordinary steps: the candidate (6.14) with the previous (6.15)'s multipliers,
        docs/vehicles.md "Session 14"); ignored when it is not one
        (:meth:`_with_duals`). ``second_duals`` the same for the attempt from
        ``second_start`` (else zero multipliers).

        ``second_start`` (optional, same forms): when the first attempt fails, the first
        solver is tried once more from this point *before* the cold-start retries (it
        counts as one more attempt; e.g. a known feasible point, as the PCBF filter's
        certified shifted plan for (2.23)). ``second_solver`` picks the solver of that
        attempt: 0 the first solver, ``k >= 1`` that of the ``k``-th retry, ``-1`` the last
        of the chain (:func:`chain_solver_index`; e.g. ``structured-ip``'s IPOPT, which
        converged from the obstacle car's shifted plan where its interior-point solver on the
        stage-ordered NLP stalls: docs/obstacles.md "session 13").

        ``lead`` (optional): the index of an entry of :attr:`retries` that runs *first*,
        from its cold start, before the first solver (the recovery steps of Algorithms 5.2
        and 6.4: :func:`~balustrade.backends.recovery.recovery_lead`); the chain then runs
        as usual, the lead counting as the first attempt and not run again.

        A failed solve is retried from a cold start with each entry of :attr:`retries`
        in turn (see :func:`default_retries`), except a retry that would run a solver
        from a start it already ran from in this solve (:func:`_same_start`: the cold
        retry of ``structured-ip`` after a cold first attempt); ``Solution.message`` and
        ``Solution.solver`` say when a retry was used. If no attempt converges but one
        ended primal feasible (rows within 1e-8 relative), it is returned with status
        ``"feasible"`` (not a success: feasible, not certified optimal; the message keeps
        the solver's own return status). Otherwise, if an attempt reported infeasibility
        (IPOPT's ``Infeasible_Problem_Detected``; sqpmethod itself cannot tell an
        infeasible problem from a failed line search, but its default retry chain ends
        with IPOPT), the status is ``"infeasible"``; else the first attempt's status
        (``failed``, ``max_iterations``).

        Real-time mode (issue #14 §5): when the target has a budget
        (:meth:`~balustrade.backends.targets.Target.with_budget`, the ``"real-time"``
        preset), a first attempt stopped by it (iteration cap, IPOPT's wall-time limit) is
        returned at once as *truncated* (:meth:`_truncated`): status ``max_iterations``,
        ``Solution.truncated`` and the primal residual at the iterate; no retry runs after
        it (that would break the time bound) and it is never rescued as ``"feasible"``.

        An attempt whose iterates diverged (IPOPT's ``Diverging_Iterates``) or whose
        objective is below :data:`UNBOUNDED_OBJECTIVE` or not finite is ``failed`` with a
        message saying the problem appears unbounded (:func:`_unbounded`); when no attempt
        converged, such an attempt is returned, never rescued as ``"feasible"`` (a point
        of an unbounded problem is no answer to use in a closed loop).
        """
        if lead is not None and (isinstance(lead, bool) or not isinstance(lead, int | np.integer)
                                 or not 0 <= lead < len(self.retries)):
            raise SolverError(f"{self.ocp.name}: lead must be the index of a retry "
                              f"(0 … {len(self.retries) - 1}), got {lead!r}")
        p = self.ocp.pack_parameters(params)
        second_k = chain_solver_index(second_solver, len(self.retries))
        guess = self._with_duals(self._initial_guess(warm_start, p), duals_from, p)
        attempts, ran = [], []  # (solver, start) of every attempt run so far
        if lead is not None and self.budget is None:  # (a budget has no retries to lead)
            led, cold = self._retry_solvers()[lead], self._initial_guess(None, p)
            attempts.append(self._solve_with(led, p, cold))
            ran.append((led, cold))
            if attempts[0].success:
                return attempts[0]
        sol = self._solve_with(self.solver, p, guess)
        if self.budget is not None and sol.status == Status.MAX_ITERATIONS:
            return self._truncated(sol, p)  # no retry, no rescue: the time bound holds
        attempts.append(sol)
        ran.append((self.solver, guess))
        if second_start is not None and not sol.success:
            # not in ``ran``: the retries run cold, and the C's ran_before compares them with
            # the cold attempts only (a second start equal to the cold one is not skipped)
            attempts.append(self._solve_with(
                self._retry_solvers()[second_k - 1] if second_k else self.solver, p,
                self._with_duals(self._initial_guess(second_start, p), second_duals, p,
                                 keep_primal=True)))
        for solver in self._retry_solvers():
            if attempts[-1].success:
                break
            cold = self._initial_guess(None, p)
            if any(s is solver and _same_start(g, cold) for s, g in ran):
                continue  # deterministic: the same solver from the same start (skipped)
            ran.append((solver, cold))
            attempts.append(self._solve_with(solver, p, cold))
        final = attempts[-1] if attempts[-1].success else attempts[0]
        unbounded = [a for a in attempts if a.raw.get("unbounded")]
        if unbounded and not final.success:  # evidence of unboundedness beats any rescue
            final = unbounded[-1]
        elif not final.success:
            feasible = [a for a in reversed(attempts) if a.raw.get("x") is not None
                        and self._primal_feasible(a.raw["x"], p)]
            infeasible = [a for a in attempts if a.status == Status.INFEASIBLE]
            if feasible:  # no attempt converged; report a primal-feasible point as such
                final = feasible[0]
                final.status = Status.FEASIBLE
            elif infeasible:
                final = infeasible[-1]
        if len(attempts) > 1:
            final.solve_time = sum(a.solve_time for a in attempts)
            final.iterations = sum(a.iterations for a in attempts)
            final.message += " (after retries: " + ", ".join(
                f"{a.solver}: {a.message}" for a in attempts if a is not final) + ")"
        return final

    @property
    def budget(self) -> Budget | None:
        """The :class:`~balustrade.backends.targets.Budget` of the target this problem was
        compiled for (``None``: no budget, or built without a target)."""
        target = getattr(self, "target", None)
        return None if target is None else target.budget

    def _truncated(self, sol: Solution, p: np.ndarray) -> Solution:
        """A solve stopped by the budget: flagged truncated, with the largest violation of a
        constraint row or bound at its iterate (so callers can tell a feasible from an
        infeasible stop); its status stays ``max_iterations``."""
        sol.truncated = True
        x = sol.raw.get("x")
        sol.primal_residual = np.nan if x is None else self._primal_residual(x, p)
        sol.message += (f" (truncated by the budget {self.budget}: primal residual "
                        f"{sol.primal_residual:.3g})")
        return sol

    def _primal_residual(self, w_all: np.ndarray, p: np.ndarray) -> float:
        """The largest violation (absolute) of a constraint row or a variable bound at
        ``w_all`` (``nan`` if the point is not finite)."""
        if not np.all(np.isfinite(w_all)):
            return float("nan")
        g = self._g(w_all, p)
        parts = [g - self.ubg, self.lbg - g, w_all - self.ubx, self.lbx - w_all]
        return float(max(0.0, *(np.max(v, initial=0.0) for v in parts)))

    def _g(self, w_all: np.ndarray, p: np.ndarray) -> np.ndarray:
        """The constraint rows of the solver's NLP at ``w_all``."""
        if self._g_function is None:
            self._g_function = ca.Function("g", [self.nlp["x"], self.nlp["p"]],
                                           [self.nlp["g"]])
        return np.asarray(self._g_function(w_all, p)).reshape(-1)

    def _retry_solvers(self) -> list[ca.Function]:
        """The solvers of :attr:`retries`, built on first use."""
        if self._retry is None:
            self._retry = [
                self.solver if (name == self.solver_name and not overrides) else
                _nlpsol(f"{self.ocp.name}_retry{k + 1}", name, self.nlp,
                        self.with_derivatives({**self.options, **overrides})
                        if name == self.solver_name else self._retry_options(name, overrides))
                for k, (name, overrides) in enumerate(self.retries)]
        return self._retry

    def _retry_options(self, name: str, overrides: dict) -> dict:
        """The options of a retry on another plugin ``name``: its defaults updated by
        ``overrides`` (:func:`solver_options`) and, for a target the C emitters generate
        (:attr:`as_emitted`), the stopping rule of that plugin's emitted C
        (:data:`EMITTED_STOP_OPTIONS`), so that Python and its C run the same iterations
        (issue #14, "C = Python"; session 13: on the lane change, seed 8 step 1, Python's
        IPOPT retry of (5.16) stopped at its acceptable level, ``optimal_inaccurate``, where
        the C's went on to the full tolerance: inputs 1.8e-13 apart, then 2.6e-8)."""
        opts = solver_options(name, overrides)
        if self.as_emitted:
            opts = {**opts, **EMITTED_STOP_OPTIONS.get(name, {})}
        return opts

    def with_derivatives(self, opts: dict, derivatives: dict | None = None) -> dict:
        """``opts`` plus the shared derivative functions (``derivatives``, default this
        problem's own) when they apply to ``opts``."""
        derivatives = self.derivatives if derivatives is None else derivatives
        if not derivatives or opts.get("hessian_approximation", "exact") != "exact":
            return opts
        return {**opts, **derivatives}

    def _solve_with(self, solver: ca.Function, p: np.ndarray, guess: tuple) -> Solution:
        x0, lam_x0, lam_g0 = guess
        p_dm = ca.DM(p)
        start = time.perf_counter()
        try:
            res = solver(x0=x0, p=p_dm, lbx=self._dm["lbx"], ubx=self._dm["ubx"],
                         lbg=self._dm["lbg"], ubg=self._dm["ubg"], lam_x0=lam_x0,
                         lam_g0=lam_g0)
            elapsed = time.perf_counter() - start
            stats = solver.stats()
        except RuntimeError as exc:  # CasADi raises on evaluation errors (NaN, etc.)
            elapsed = time.perf_counter() - start
            return self._failed(p, elapsed, str(exc))
        w_all = np.asarray(res["x"]).reshape(-1)
        # multipliers of the declared problem (the solver's objective and rows are scaled)
        lam_g = np.asarray(res["lam_g"]).reshape(-1) / self.objective_scale
        if self.row_scale is not None:
            lam_g = lam_g * self.row_scale
        lam_x = np.asarray(res["lam_x"]).reshape(-1) / self.objective_scale
        x_orig = res["x"]
        if self.stages is not None:  # back from stage order to the layout's order
            lam_g, lam_x = self.stages.row_dual(lam_g), self.stages.primal(lam_x)
            # fatrop relaxes every bound by ~1e-8 relative (no option turns this off): a
            # slack xi >= 0 weighted by alpha_f = 1e6 would read -1e-2; project onto the
            # bounds (rows stay satisfied to the same 1e-8)
            x_orig = np.clip(self.stages.primal(w_all), *self._layout_bounds)
        layout = self.layout
        w = np.asarray(x_orig).reshape(-1)[: layout.user_size]
        status = _status(stats)
        # sqpmethod can return Solve_Succeeded at a point far off its constraints (seen on
        # the lane change (6.15) after a failed first attempt: residual 8e7); the C emitted
        # for it tests its own KKT residuals and rejects such a point, so Python must too
        flagged = status == Status.OPTIMAL and solver.class_name() == "Sqpmethod" \
            and not self._primal_feasible(w_all, p, SQP_FEASIBILITY_TOL)
        # sqpmethod's own test has no complementarity: an interior-point QP solver stopped
        # at its iteration limit hands it multipliers of a central-path point, not of the
        # optimum (sqp_complementarity)
        noncomplementary = status == Status.OPTIMAL and not flagged \
            and solver.class_name() == "Sqpmethod" \
            and self._qpsol_of(solver) in INEXACT_QPSOLS \
            and self._complementarity(w_all, res, p) > SQP_COMPLEMENTARITY_TOL
        if flagged or noncomplementary:
            status = Status.FAILED
        dual = {name: lam_g[s] for name, s in self.block_slices.items()}
        for name, arr in layout.unpack(lam_x, user_only=True).items():
            dual[f"bound:{name}"] = arr
        # the declared cost at the returned point (exact; the epigraph value may differ by
        # solver tolerances or, for the 2-norm, by up to NORM2_EPS/4 per term); called with
        # the solver's own DM outputs (no numpy round trip on the closed-loop hot path)
        objective = self.inverse.objective(x_orig, p_dm) if np.all(np.isfinite(w)) \
            else np.nan
        message = _message(stats)
        if flagged:
            message += (f": reported converged at a point violating its constraints by "
                        f"{self._primal_residual(w_all, p):.3g}")
        if noncomplementary:
            message += (f": reported converged, but its multipliers are not complementary "
                        f"(largest |lambda_i| * gap_i {self._complementarity(w_all, res, p):.3g}"
                        f" > {SQP_COMPLEMENTARITY_TOL:g}; the QP solver stopped early)")
        why = _unbounded(message, objective)
        if why is not None:
            status, message = Status.FAILED, f"{message}: the problem appears unbounded ({why})"
        return Solution(status=status, objective=objective,
                        primal=layout.unpack(w, user_only=True), dual=dual,
                        solve_time=elapsed,
                        iterations=int(stats.get("iter_count", 0)), backend="casadi",
                        solver=_SOLVER_NAMES.get(solver.class_name(), solver.class_name()),
                        p=p,  # w is derived from primal
                        message=message,
                        raw={"x": w_all, "lam_x": lam_x, "lam_g": lam_g,
                             "unbounded": why is not None,
                             # which function of the chain answered (retries equal to the
                             # first solver share its function, as in the emitted C)
                             "function": solver.name(),
                             # the solver's own outputs, passed back as a warm start as-is
                             "dm": (res["x"], res["lam_x"], res["lam_g"])})

    def _primal_feasible(self, w_all: np.ndarray, p: np.ndarray, tol: float = 1e-8) -> bool:
        """Bounds and constraint rows hold up to ``tol`` (rows scaled by ``1 + |g|``)."""
        if not np.all(np.isfinite(w_all)):
            return False
        g = self._g(w_all, p)
        scale = 1.0 + np.abs(g)
        return bool(np.all(g - self.ubg <= tol * scale) and np.all(self.lbg - g <= tol * scale)
                    and np.all(w_all - self.ubx <= tol) and np.all(self.lbx - w_all <= tol))

    def complementarity_weight(self) -> float | None:
        """For an sqpmethod whose QP solver is one of :data:`INEXACT_QPSOLS`: ``tol_du /
        SQP_COMPLEMENTARITY_TOL``, the weight by which the emitted C's KKT function
        (:mod:`balustrade.codegen.emit`) adds the complementarity error to its ``du_inf``,
        so its test ``du_inf < tol_du`` includes :meth:`_complementarity`'s; else ``None``."""
        if self.solver_name != "sqpmethod" or self._qpsol_of(self.solver) not in INEXACT_QPSOLS:
            return None
        return float(self.options.get("tol_du", 1e-6)) / SQP_COMPLEMENTARITY_TOL

    def _qpsol_of(self, solver: ca.Function) -> str:
        """sqpmethod's QP solver plugin in ``solver`` (the first attempt or a retry)."""
        if solver is self.solver:
            return str(self.options.get("qpsol", "qrqp"))
        for (name, over), fn in zip(self.retries, self._retry or []):
            if fn is solver:
                opts = {**self.options, **over} if name == self.solver_name else \
                    solver_options(name, over)
                return str(opts.get("qpsol", "qrqp"))
        return "qrqp"

    def _complementarity(self, w_all: np.ndarray, res: dict, p: np.ndarray) -> float:
        """The largest complementarity error of the solver's own primal-dual point, in its
        own (scaled) units (:func:`complementarity_expr`, the expression the emitted C's KKT
        test uses too). ``inf`` for a non-finite point."""
        lam_g = np.asarray(res["lam_g"], dtype=float).reshape(-1)
        lam_x = np.asarray(res["lam_x"], dtype=float).reshape(-1)
        if not (np.all(np.isfinite(w_all)) and np.all(np.isfinite(lam_g))
                and np.all(np.isfinite(lam_x))):
            return float("inf")
        if self._complementarity_fn is None:  # built once, on the first solve that needs it
            w, g = ca.SX.sym("w", lam_x.size), ca.SX.sym("g", lam_g.size)
            lx, lg = ca.SX.sym("lam_x", lam_x.size), ca.SX.sym("lam_g", lam_g.size)
            self._complementarity_fn = ca.Function(
                "complementarity", [w, g, lx, lg], [complementarity_expr(self, w, g, lx, lg)])
        return float(self._complementarity_fn(w_all, self._g(w_all, p), lam_x, lam_g))

    def _initial_guess(self, warm: Solution | dict | None, p: np.ndarray | None = None
                       ) -> tuple[np.ndarray, np.ndarray | float, np.ndarray | float]:
        # a truncated iterate is continued primal-dual (real-time iterations: the SQP picks
        # up where the budget stopped it at the previous step)
        if isinstance(warm, Solution) and warm.backend == "casadi" and "dm" in warm.raw \
                and warm.raw["x"].size == self.lbx.size and (
                    warm.success or (warm.truncated and np.all(np.isfinite(warm.raw["x"])))):
            return warm.raw["dm"]
        if isinstance(warm, Solution):
            w_user = warm.w  # derived from warm.primal on each access: once here
            if not np.all(np.isfinite(w_user)):
                w_user = self.ocp.pack_variables({})
        elif isinstance(warm, dict):
            w_user = self.ocp.pack_variables(warm)
        else:
            w_user = self.ocp.pack_variables({})
        if self.stages is not None:  # the layout's order → stage order (copies, sums)
            w_all = np.concatenate([w_user, self._x0_layout[self.layout.user_size:]])
            return self.stages.staged(w_all, np.zeros(0) if p is None else p), 0.0, 0.0
        return np.concatenate([w_user, self._x0[self.layout.user_size:]]), 0.0, 0.0

    def _with_duals(self, guess: tuple, duals_from: Solution | None, p: np.ndarray,
                    keep_primal: bool = False) -> tuple:
        """``guess`` with the multipliers of ``duals_from`` when that is a converged CasADi
        solution of this problem (the emitted C keeps the multipliers of the last
        converged solve: ``bal/multiobj.c``); else ``guess``. Non-finite multipliers give
        what the C's ``P_solve_lead`` starts from then (it replaces a non-finite warm
        start by the cold start): the cold start, or with ``keep_primal`` (a second
        start) ``guess``'s primal point with zero multipliers."""
        if not (isinstance(duals_from, Solution) and duals_from.backend == "casadi"
                and duals_from.success and "dm" in duals_from.raw
                and duals_from.raw["x"].size == self.lbx.size):
            return guess
        _, lam_x, lam_g = duals_from.raw["dm"]
        if not (np.all(np.isfinite(np.asarray(lam_x, dtype=float)))
                and np.all(np.isfinite(np.asarray(lam_g, dtype=float)))):
            return (guess[0], 0.0, 0.0) if keep_primal else self._initial_guess(None, p)
        return guess[0], lam_x, lam_g

    def _failed(self, p: np.ndarray, elapsed: float, message: str) -> Solution:
        w = np.full(self.layout.user_size, np.nan)
        return Solution(status=Status.FAILED, objective=np.nan,
                        primal=self.ocp.unpack_variables(w), dual={}, solve_time=elapsed,
                        iterations=0, backend="casadi", solver=self.solver_name, p=p,
                        message=message)


def chain_solver_index(which: int, n_retries: int) -> int:
    """The attempt index (0: the first solver, ``k``: the ``k``-th retry) that ``which``
    names in a chain of ``n_retries`` retries; ``-1`` is the last of the chain (the first
    solver when there is no retry). Refuses an index outside the chain."""
    if isinstance(which, bool) or not isinstance(which, int | np.integer):
        raise SolverError(f"second_solver must be an int, got {which!r}")
    k = n_retries if which == -1 else int(which)
    if not 0 <= k <= n_retries:
        raise SolverError(f"second_solver {which} is outside the chain (first solver 0, "
                          f"retries 1..{n_retries}, or -1 for the last)")
    return k


def _same_start(a: tuple, b: tuple) -> bool:
    """Whether two starts ``(x0, lam_x0, lam_g0)`` of one solver are equal value for value
    (a scalar multiplier start stands for that value in every entry).

    Used to skip a retry identical to an attempt that already ran (issue #14, session 12):
    the default ``structured-ip`` chain (fatrop, cold fatrop, IPOPT) re-ran fatrop from the
    same cold start when the first attempt was itself cold; the solvers are deterministic,
    so that run repeated the first one's iterations and answer (its statuses, points and
    rescues are those of the first attempt: dropping it changes no result). The emitted C
    skips the same retry (``bal/problem.c``)."""
    for u, v in zip(a, b, strict=True):
        u, v = np.asarray(u, dtype=float).ravel(), np.asarray(v, dtype=float).ravel()
        if u.size != v.size and 1 not in (u.size, v.size):
            return False
        if not np.all(u == v):  # (a NaN start is never the same start)
            return False
    return True


#: options of a plugin's emitted C that change where it stops (part of
#: :data:`balustrade.backends.emittable.STATUS_OPTIONS`, which adds ``error_on_fail`` for the
#: C's verdict): the emitted IPOPT takes no acceptable stop after a run of acceptable
#: iterates (it can still end at its acceptable level otherwise; the C then reads IPOPT's
#: return status and reports ``optimal_inaccurate`` as Python does:
#: emittable.ACCEPTABLE_STOP). :meth:`CasadiCompiled._retry_options` gives the retries of an
#: as-emitted target the same rule.
EMITTED_STOP_OPTIONS: dict[str, dict] = {"ipopt": {"ipopt.acceptable_iter": 0}}

#: the balustrade option (in a target's options, never passed to ``nlpsol``) choosing the
#: NLP the solver is built on
LOWERING_OPTION = "lowering"
#: the lowerings of :data:`LOWERING_OPTION`: ``"expanded"`` (default) — one SX graph of
#: ``f`` and ``g``, derivatives written out for every stage (fastest from Python);
#: ``"compact"`` — MX with each dynamics block one stage function mapped over the horizon
#: (:func:`~balustrade.backends.passes.casadi_nlp.compact_nlp`): its derivatives appear once
#: in generated C (the default of the C emitters, :mod:`balustrade.codegen.emit`)
LOWERINGS = ("expanded", "compact")
#: the value of :data:`LOWERING_OPTION` the emitted presets carry: the lowering Python
#: solves when its C is generated (``codegen.emit.EMIT_LOWERING``, ``"compact"``) for
#: solvers in the layout's order, and ``"expanded"`` for the stage-ordered ones (fatrop,
#: sqpmethod + hpipm), whose Python NLP is the expanded one in stage order and whose C is
#: the compact lowering permuted into that order. So ``fast-sqp`` with ``qpsol="hpipm"``
#: or with the solver fatrop still compiles (issue #14, session 12 review), while an
#: explicit ``"compact"`` with a stage-ordered solver is refused.
AS_EMITTED = "as-emitted"


def _lowering(name: str, value: object) -> str:
    if value not in LOWERINGS:
        raise SolverError(f"{name}: option {LOWERING_OPTION!r} must be one of "
                          f"{', '.join(map(repr, (*LOWERINGS, AS_EMITTED)))}, got {value!r}")
    return str(value)


#: a solve that sqpmethod reports converged is ``failed`` when a constraint row (relative to
#: ``1 + |g|``) or a bound is violated by more than this (:meth:`CasadiCompiled._solve_with`)
SQP_FEASIBILITY_TOL = 1e-6

#: a solve that sqpmethod reports converged is ``failed`` when, with a QP solver that can
#: return an unconverged primal-dual point (:data:`INEXACT_QPSOLS`), the largest
#: complementarity error ``|λ_i| · gap_i`` of its point (solver units) exceeds this
#: (:meth:`CasadiCompiled._complementarity`). Why (issue #14): sqpmethod stops when the
#: primal infeasibility is below ``tol_pr`` and ``‖∇L‖`` below ``tol_du`` at the multipliers
#: of its last QP, and never tests complementarity; HPIPM (``structured-sqp``), an interior
#: point method, stopped at its ``iter_max`` returns a central-path point whose multipliers
#: are positive on inactive rows. Measured on the staged RAPSF QP (4.5) (toy of
#: tests/conftest.py, N = 6, 30 states, HPIPM ``iter_max`` 4–15): "optimal" with ``v_0`` up
#: to 3.8e-3 off IPOPT's optimum (``tol_du`` 1e-6; 5.9e-2 with ``tol_du`` 1e-4), at
#: complementarity errors 7e-8 … 1.5e-4; at the default ``iter_max`` 200 the errors stayed
#: <= 3.5e-9 on that toy. Equality rows are skipped and slacks at rounding level count as 0
#: (:data:`COMPLEMENTARITY_SLACK_ROUNDING`): without that, 9 of 40 converged pendulum (2.24)
#: solves with multipliers up to 3e8 were failed. The same with OSQP (ADMM) capped at
#: ``max_iter`` 25/50 on the plain (4.5): "optimal" 4.5e-2/9e-3 off at 9.4e-3/3.7e-4; at
#: its default (20 000) <= 7.1e-10 (tests/test_status_mapping.py)
SQP_COMPLEMENTARITY_TOL = 1e-8

#: the rounding a slack ``bound − value`` may carry, relative to ``1 + |bound|``: a slack
#: below it counts as zero in the complementarity test. Why: with HPIPM no objective
#: scaling applies, and the PCBF's ``α_f = 1e6`` gives multipliers of 1e6–3e8; a slack of
#: 3e-14 on an active row then made ``|λ|·gap`` exceed :data:`SQP_COMPLEMENTARITY_TOL`, and 9
#: of 40 converged pendulum (2.24) solves (objective equal to IPOPT's to 4e-12) were failed
#: (review, session 11; tests/test_status_mapping.py)
COMPLEMENTARITY_SLACK_ROUNDING = 1e-12


def complementarity_expr(c: CasadiCompiled, w: object, g: object, lam_x: object,
                         lam_g: object) -> object:
    """``max |λ_i| · gap_i`` over the inequality rows and bounds of ``c`` as a CasADi
    expression in the primal ``w``, the rows ``g`` and the multipliers: ``gap_i`` is the
    slack to the bound the sign of ``λ_i`` points to (CasADi: ``λ > 0`` upper, ``λ < 0``
    lower), on the feasible side only (an overshoot is the feasibility test's business) and
    less :data:`COMPLEMENTARITY_SLACK_ROUNDING` ``· (1 + |bound|)``, never negative; a
    multiplier pointing to an infinite bound (its row cannot be active: a sign error) counts
    as ``|λ_i|``; equality rows (``lo == up``) have no complementarity condition and are
    skipped. One definition for :meth:`CasadiCompiled._complementarity` and the emitted C's
    KKT test (:func:`balustrade.codegen.emit._kkt_function`)."""
    parts = [ca.DM(0)]
    for lam, val, lo, up in ((lam_x, w, c.lbx, c.ubx), (lam_g, g, c.lbg, c.ubg)):
        if not np.size(lo):
            continue
        lo_a = np.broadcast_to(np.asarray(lo, dtype=float), (lam.numel(),))
        up_a = np.broadcast_to(np.asarray(up, dtype=float), (lam.numel(),))
        inequality = ca.DM((lo_a != up_a).astype(float))
        for bound, mult, sign in ((up_a, ca.fmax(lam, 0), 1.0),
                                  (lo_a, ca.fmax(-lam, 0), -1.0)):
            finite = np.isfinite(bound)
            mask = ca.DM(finite.astype(float))
            safe = np.where(finite, bound, 0.0)
            slack = sign * (ca.DM(safe) - val)
            rounding = ca.DM(COMPLEMENTARITY_SLACK_ROUNDING * (1.0 + np.abs(safe)))
            gap = mask * ca.fmax(slack - rounding, 0) + (1 - mask)
            parts.append(ca.mmax(inequality * mult * gap))
    return ca.mmax(ca.vertcat(*parts))


#: sqpmethod's QP solvers whose returned point can be an unconverged interior-point or ADMM
#: iterate (HPIPM, OSQP). Not qrqp: active set, its points are complementary by
#: construction, and its emitted C (the fast-sqp chain, C = Python on 1000 states) has no
#: complementarity test
INEXACT_QPSOLS = ("hpipm", "osqp")

#: an objective below this (IPOPT's default ``diverging_iterates_tol`` is 1e20) is taken as
#: evidence that the problem is unbounded below
UNBOUNDED_OBJECTIVE = -1e19


def _unbounded(message: str, objective: float) -> str | None:
    """Why a solver run looks unbounded below, or ``None``: diverging iterates (IPOPT's
    ``Diverging_Iterates``), an objective below :data:`UNBOUNDED_OBJECTIVE`, or a
    non-finite objective at a finite point."""
    if message == "Diverging_Iterates":
        return "diverging iterates"
    if np.isnan(objective):
        return None  # no finite point: an evaluation failure, not unboundedness
    if not np.isfinite(objective) or objective < UNBOUNDED_OBJECTIVE:
        return f"objective {objective:.3g}"
    return None


def shared_derivatives(nlp: dict, solver: str, options: dict) -> dict[str, ca.Function]:
    """For an exact-Hessian ``sqpmethod``: its derivative functions built once, as the
    ``nlpsol`` options ``jac_fg`` (``f``, ``∇f``, ``g``, ``∂g/∂x``) and ``hess_lag``
    (``∇²ₓ(λ_f f + λ_gᵀ g)``, full symmetric), else ``{}``.

    Why (issue #14): ``nlpsol`` derives these functions anew for every solver object, and
    on a nonlinear horizon problem the expanded SX derivatives are most of the generated C
    (cart-pole PCBF, RK4, N = 20: ≈ 19 000 lines for the Hessian, 11 000 for the
    Jacobian, 8 000 for ``nlp_grad`` per solver). ``nlp_fg`` and ``nlp_grad`` go in as the
    ``cache`` option (nlpsol looks them up by name). The same Function objects passed to
    the first attempt and to each ``sqpmethod`` retry are generated once (CasADi's code
    generator emits a Function object once), and built once in Python. The math is that
    of ``sqpmethod``'s own functions."""
    if not _shares_derivatives(solver, options):
        return {}
    x, p, f, g = nlp["x"], nlp["p"], nlp["f"], nlp["g"]
    sym = type(x).sym
    lam_f, lam_g = sym("lam_f"), sym("lam_g", g.numel())
    lag = lam_f * f + ca.dot(lam_g, g) if g.numel() else lam_f * f
    jac_fg = ca.Function("nlp_jac_fg", [x, p], [f, ca.gradient(f, x), g, ca.jacobian(g, x)],
                         ["x", "p"], ["f", "grad_f_x", "g", "jac_g_x"])
    hess = ca.Function("nlp_hess_l", [x, p, lam_f, lam_g], [ca.hessian(lag, x)[0]],
                       ["x", "p", "lam_f", "lam_g"], ["hess_gamma_x_x"])
    # nlpsol's own helpers, looked up by name in its function cache before it derives them
    fg = ca.Function("nlp_fg", [x, p], [f, g], ["x", "p"], ["f", "g"])
    grad = ca.Function("nlp_grad", [x, p, lam_f, lam_g],
                       [f, g, ca.gradient(lag, x), ca.gradient(lag, p)],
                       ["x", "p", "lam_f", "lam_g"], ["f", "g", "grad_gamma_x", "grad_gamma_p"])
    return {"jac_fg": jac_fg, "hess_lag": hess, "cache": {"nlp_fg": fg, "nlp_grad": grad}}


def _shares_derivatives(solver: str, options: dict) -> bool:
    """Whether :func:`shared_derivatives` applies: an exact-Hessian ``sqpmethod``."""
    return solver == "sqpmethod" and options.get("hessian_approximation", "exact") == "exact"


def sqp_retry_strategies(options: dict) -> list[str]:
    """Hessian convexifications for cold-start ``sqpmethod`` retries: the eigenvalue-based
    ones (clip, reflect) other than the one in ``options``. ``regularize`` and ``none`` are
    never used: CasADi 3.8's qrqp corrupts the heap with them on small problems."""
    strategy = options.get("convexify_strategy", "none")
    return [s for s in ("eigen-clip", "eigen-reflect") if s != strategy]


def default_retries(solver: str, options: dict) -> list[tuple[str, dict]]:
    """The default retry chain: for ``sqpmethod`` the strategies of
    :func:`sqp_retry_strategies` (all code-generatable), then IPOPT as a last resort; for
    any other solver one cold-start retry of the same solver."""
    if solver == "sqpmethod":
        return [("sqpmethod", {"convexify_strategy": s}) for s in sqp_retry_strategies(options)] \
            + [("ipopt", {})]
    return [(solver, {})]


_SOLVER_NAMES = {"Sqpmethod": "sqpmethod", "IpoptInterface": "ipopt",
                 "FatropInterface": "fatrop"}

#: ``return_status`` strings of IPOPT and sqpmethod → Solution statuses (anything else,
#: e.g. sqpmethod's ``Search_Direction_Becomes_Too_Small`` or IPOPT's
#: ``Restoration_Failed``, is ``failed``: neither certifies anything)
_RETURN_STATUS = {
    "Solve_Succeeded": Status.OPTIMAL,
    "Solved_To_Acceptable_Level": Status.OPTIMAL_INACCURATE,  # CasADi reports success=True
    "Infeasible_Problem_Detected": Status.INFEASIBLE,         # IPOPT's local infeasibility
    "Maximum_Iterations_Exceeded": Status.MAX_ITERATIONS,
    "Maximum_CpuTime_Exceeded": Status.MAX_ITERATIONS,
    "Maximum_WallTime_Exceeded": Status.MAX_ITERATIONS,
}


#: fatrop's own return flags (``stats()["fatrop"]["return_flag"]``, fatrop 1.1.8's
#: ``IpSolverReturnFlag``; CasADi's ``return_status`` is only 0 = success / nonzero) → the
#: message and status of the run.
#:
#: "Acceptable" (``tol_acceptable`` held for ``acceptable_iter`` iterations, fatrop's own
#: ``tolerance`` not met; note ``acceptable_iter`` 0 stops at the first acceptable iterate,
#: unlike IPOPT's 0 = never) is *not* a success here (issue #14, "C = Python"): the
#: emitted C cannot tell it from a failure (its fatrop returns nonzero unless fatrop ended
#: with ``Success``: ``backends.emittable.STATUS_OPTIONS``), retries it and, if no retry
#: converges, reports the point ``BAL_FEASIBLE`` when it is primal feasible. So the run is
#: ``failed`` here: :meth:`CasadiCompiled.solve` retries it with the same chain and, if
#: nothing converges, rescues it as ``feasible`` by the same primal test — the status the C
#: reports, and an honest one (a point, not a certified optimum: the PCBF step then takes
#: its cost only as an upper bound on ``h_PB``; tests/test_status_mapping.py).
_FATROP_FLAGS: dict[int, tuple[str, Status]] = {
    0: ("fatrop: Success", Status.OPTIMAL),
    1: ("fatrop: MaxIterExceeded", Status.MAX_ITERATIONS),
    2: ("fatrop: StopAtAcceptablePoint", Status.FAILED),
    3: ("fatrop: LocalInfeasibility", Status.INFEASIBLE),
    4: ("fatrop: LineSearchFailed", Status.FAILED),
    5: ("fatrop: ErrorInStepComputation", Status.FAILED),
}


def _fatrop_flag(stats: dict) -> tuple[str, Status] | None:
    flag = stats.get("fatrop", {}).get("return_flag") if isinstance(
        stats.get("fatrop"), dict) else None
    return None if flag is None else _FATROP_FLAGS.get(int(flag),
                                                       (f"fatrop: flag {flag}", Status.FAILED))


def _stale_success(stats: dict) -> bool:
    """``return_status`` says ``Solve_Succeeded`` while ``success`` is False: the run did
    not converge, and the string is apparently left over from an earlier run of the same
    solver (CasADi 3.8.2's sqpmethod built afresh has no ``return_status`` after the same
    run, and ``stats()`` raises). Seen on the lane change (session 15, seed 41 step 10, (5.16)): the
    SQP stopped after one iteration at a point off its rows by 8.1e-7 with a dual
    infeasibility of 0.8, above ``tol_pr`` 1e-9 and ``tol_du`` 1e-6, and Python used it as
    optimal, while the emitted C, which tests its own KKT residuals, retried and found a
    point of lower cost. Such a run is ``failed``."""
    return str(stats.get("return_status", "")) == "Solve_Succeeded" and \
        stats.get("success") is False


def _message(stats: dict) -> str:
    """The solver's return status as text (fatrop's numeric flag decoded; a stale success
    string, :func:`_stale_success`, named as such)."""
    fatrop = _fatrop_flag(stats)
    if fatrop is not None:
        return fatrop[0]
    if _stale_success(stats):
        return "stopped without converging (success false; a stale Solve_Succeeded)"
    return str(stats.get("return_status", ""))


def _status(stats: dict) -> Status:
    """The :class:`Solution` status of one solver run from its ``stats()``."""
    fatrop = _fatrop_flag(stats)
    if fatrop is not None:
        return fatrop[1]
    msg = str(stats.get("return_status", ""))
    if _stale_success(stats):
        return Status.FAILED
    if msg in _RETURN_STATUS:
        return _RETURN_STATUS[msg]
    if stats.get("success", False):  # another plugin's success string
        return Status.OPTIMAL
    low = msg.lower()
    if "infeasible" in low:
        return Status.INFEASIBLE
    if "maximum" in low or "max_iter" in low:
        return Status.MAX_ITERATIONS
    return Status.FAILED
