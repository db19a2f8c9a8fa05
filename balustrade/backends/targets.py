"""Solver targets: which backend, which solver, which options, which retry chain — as data.

A :class:`Target` is the one place where a solver is chosen and tuned. Formulations
(``problems/``) never name a solver; controllers (``control/``), the sampler (``learn/``),
the reproductions and the tests take a target (or a preset name) and hand it to
:func:`balustrade.backends.compile`. The presets below are the only definitions of solver
options outside the backend modules themselves (issue #13, §1).

Presets (see :data:`PRESETS`; ``docs/language.md`` explains when to use which). They are
named for what they are for, not for their solver, so code outside ``backends/`` never names
a solver (the older solver-named spellings in :data:`ALIASES` still resolve):

=====================  =========================================================================
``"exact"``            CasADi + IPOPT, tight tolerances, one cold retry. The default of
                       :func:`~balustrade.backends.compile`: exact on every smooth NLP.
``"fast-sqp"``         CasADi ``sqpmethod`` + ``qrqp`` (dense active set), eigenvalue-clipping
                       convexification, retries with the other convexification, then IPOPT.
                       The closed-loop default for small problems; the one that emits C.
                       Solves the compact lowering, the NLP its emitted C solves (as
                       ``fast-sqp-noretry``, ``robust-sqp``, ``convex-qp``, ``real-time``).
``"fast-sqp-noretry"`` ``fast-sqp`` without retries, for loops with their own fallbacks and for
                       warm-started sampling (a failed warm solve is redone by a cold twin).
``"robust-sqp"``       ``fast-sqp`` with 500 SQP iterations (the robust filter (5.16)), on the
                       compact lowering, the NLP its emitted C solves (:data:`_ROBUST_SQP`).
``"convex-qp"``        CasADi ``sqpmethod`` with DAQP (dual active set, proximal iterations for
                       the singular Hessians of filter costs) as QP solver; on a convex QP one
                       SQP iteration. Retries: the other convexification only (no IPOPT), the
                       chain its emitted C runs, so Python and C agree without a mirror mode.
                       Its C links libdaqp (shipped in the casadi wheel). For the RAPSF QP
                       (4.5), where qrqp cycles (docs/deploy_c.md).
``"long-horizon"``     IPOPT with the adaptive barrier update (long horizons, e.g. the
                       rendezvous N = 200).
``"sampling-cold"``    IPOPT demanding absolute complementarity (slacks weighted by
                       α_f = 1e6), for sampling value functions cold.
``"sampling-warm"``    ``sampling-cold`` with IPOPT's warm-start options, for warm solves
                       along sampling paths.
``"structured-ip"``    CasADi ``fatrop`` (interior point, O(N) per iteration) on the stage-ordered
                       NLP (:mod:`~balustrade.backends.passes.stage_order`), one cold retry,
                       then IPOPT. Its C links libfatrop and libblasfeo (shipped in the casadi
                       wheel). For horizon OCPs only (refused otherwise, naming the block),
                       and not with a 2-norm cost term (a fatrop solve can hang there:
                       :func:`~balustrade.backends.casadi_backend._refuse_fatrop_hang`).
                       The hang's mechanism (an unbounded regularization loop on an
                       indefinite KKT matrix) is general and fatrop has no time limit:
                       on nonlinear dynamics its safety rests on the states measured
                       (docs/engines.md), not on a guarantee — not a closed-loop default.
``"structured-ip-noretry"`` fatrop alone, no retry (what its emitted C runs; benchmarks, tests).
``"structured-sqp"``   ``sqpmethod`` with HPIPM (Riccati-based QP, O(N)) as QP solver on the
                       stage-ordered NLP; retries as ``fast-sqp``. C links libhpipm, libblasfeo.
``"cvxpy"``            cvxpy: PIQP for LPs/QPs, Clarabel for conic problems, tight tolerances.
``"conic"``            cvxpy + Clarabel, tight tolerances (SOCPs, SDPs).
``"fast-convex"``      the direct backend: the convex OCP lowered once to PIQP (LPs/QPs) or
                       Clarabel (cones) through their own interfaces, only ``q``, ``b``
                       updated per solve; tight tolerances. Refuses nonconvex OCPs.
``"fast-convex-conic"`` ``fast-convex`` with Clarabel also for LPs/QPs.
``"fast-convex-qp"``   ``fast-convex`` with PIQP (LPs/QPs only).
``"fast-convex-rowgen"`` ``fast-convex-qp`` solving by row generation when the OCP groups its
                       rows (``ocp.row_groups``, e.g. (4.5)); exact, see ``row_generation``.
``"fast-convex-daqp"`` ``fast-convex`` with DAQP (LPs/QPs of at most 2e6 dense constraint
                       entries): a dual active-set solver kept across solves, hot-started
                       from the last working set; an answer is optimal only with DAQP's
                       "optimal" and a KKT residual <= 1e-8, else PIQP solves (opt-in).
``"fast-convex-sized"`` ``fast-convex`` choosing its engine by the lowered LP/QP's size at
                       compile time: ``fast-convex-daqp``'s engine up to
                       :data:`SIZED_DENSE_LIMIT` dense constraint entries, else PIQP
                       (cones: Clarabel); the compiled problem's ``solver_name`` and each
                       ``Solution.solver`` say which. The default of RAPSF (Algorithm 4.1).
``"recovery"``         the attempt that leads a recovery step (Algorithms 5.2 and 6.4 outside
                       the robust safe set, ``recovery_target=``): the interior-point solver,
                       run first from a cold start when the problem's retry chain has it
                       (:mod:`~balustrade.backends.recovery`); the chain follows as usual.
``"auto"``             ``fast-convex`` when the OCP classifies as convex, else ``exact``
                       (decided by :func:`~balustrade.backends.compile`, which records the
                       target it used as ``compiled.target``). Takes no solver or options.
``"sdp"``              synthesis problems (:func:`~balustrade.backends.compile_synthesis`):
                       cvxpy + Clarabel with Clarabel's own tolerances, the options every SDP
                       of balustrade (terminal CBF, RPI set, regret family) has been solved with.
``"real-time"``        a bounded-iteration mode (issue #14 §5): ``sqpmethod`` + ``qrqp`` capped
                       at :data:`REALTIME_ITERATIONS` SQP iterations, no retries, meant to be
                       warm-started from the previous step's iterate. A solve stopped by the
                       cap is reported *truncated* (``max_iterations``, never optimal).
=====================  =========================================================================

Budgets: :meth:`Target.with_budget` caps any CasADi target's iterations and/or (IPOPT only)
wall-clock seconds, mapped to the solver's own option names by :data:`BUDGET_OPTIONS`; the
backend then reports a stop by the budget as truncated and runs no retry after it.

A target is immutable; ``with_options``/``with_retries``/``with_solver`` return new targets.
"""

from __future__ import annotations

import numbers
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import Any

from balustrade.errors import SolverError

#: backends a target can name
BACKEND_NAMES = ("casadi", "cvxpy", "direct", "auto")

def _frozen(options: Mapping[str, Any] | None) -> Mapping[str, Any]:
    return MappingProxyType(dict(options or {}))


def _plain(value: Any) -> Any:
    """A deep plain-``dict`` copy of (possibly read-only, nested) options for a solver."""
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    return value


#: the NLP solver of a CasADi target that names none
_CASADI_DEFAULT_SOLVER = "ipopt"


# -- real-time mode (issue #14 §5): budgets and the "real-time" preset ----------------------
#: the SQP iteration cap of the ``"real-time"`` preset: one SQP iteration of the pendulum
#: PCBF problems costs ~0.6 ms (qrqp), so the worst case is a few ms per solve
REALTIME_ITERATIONS = 3

#: per CasADi NLP solver, the solver's own option for each budget kind (``iterations``,
#: ``seconds``); a kind a solver lacks (sqpmethod has no clock) is refused by
#: :meth:`Target.with_budget`
BUDGET_OPTIONS: dict[str, dict[str, str]] = {
    "sqpmethod": {"iterations": "max_iter"},
    "ipopt": {"iterations": "ipopt.max_iter", "seconds": "ipopt.max_wall_time"},
}

#: options a budget sets besides its bound, per solver. sqpmethod's ``min_step_size``
#: (default 1e-10; stop with ``Search_Direction_Becomes_Too_Small``) is switched off (-1:
#: no step norm is below it): under a budget an SQP runs until it converges or the budget
#: is spent (a vanishing step costs nothing more), so every stop without convergence is
#: the budget's — which is how the emitted C, which has no solver return status, tells a
#: truncated solve (``BAL_TRUNCATED``, :mod:`balustrade.codegen.status`) as Python does
BUDGET_COMPANIONS: dict[str, dict[str, Any]] = {
    "sqpmethod": {"min_step_size": -1.0},
}


@dataclass(frozen=True)
class Budget:
    """A bound on one solve: at most ``iterations`` solver iterations and/or ``seconds`` of
    wall-clock time (``None``: no bound of that kind). A solve stopped by it is *truncated*
    (:attr:`balustrade.backends.Solution.truncated`)."""

    iterations: int | None = None
    seconds: float | None = None

    def __post_init__(self) -> None:
        it, sec = self.iterations, self.seconds
        if it is not None and (isinstance(it, bool) or not isinstance(it, numbers.Integral)
                               or it < 1):
            raise SolverError(f"Budget: iterations must be a positive int or None, got {it!r}")
        if sec is not None and (isinstance(sec, bool) or not isinstance(sec, numbers.Real)
                                or not sec > 0 or sec == float("inf")):
            raise SolverError(f"Budget: seconds must be a positive finite number or None, "
                              f"got {sec!r}")
        if it is None and sec is None:
            raise SolverError("Budget: give iterations, seconds or both")
        # NumPy scalars (np.int64(3), np.float32(0.05)) are stored as plain Python numbers
        if it is not None:
            object.__setattr__(self, "iterations", int(it))
        if sec is not None:
            object.__setattr__(self, "seconds", float(sec))

    def options(self, solver: str) -> dict[str, Any]:
        """The options of CasADi solver ``solver`` that impose this budget."""
        names = BUDGET_OPTIONS.get(solver)
        if names is None:
            raise SolverError(f"Budget: no budget options known for solver {solver!r}; "
                              f"budgets work with {', '.join(BUDGET_OPTIONS)}")
        out: dict[str, Any] = {}
        for kind, value in (("iterations", self.iterations), ("seconds", self.seconds)):
            if value is None:
                continue
            if kind not in names:
                raise SolverError(f"Budget: solver {solver!r} has no {kind} budget (it takes "
                                  f"{', '.join(names)}); use another solver or that kind")
            out[names[kind]] = float(value) if kind == "seconds" else int(value)
        return {**BUDGET_COMPANIONS.get(solver, {}), **out}


@dataclass(frozen=True)
class Target:
    """Where an :class:`~balustrade.dsl.ocp.OCP` is compiled to.

    ``backend``: ``"casadi"``, ``"cvxpy"`` or ``"direct"``; ``solver``: a CasADi ``nlpsol``
    plugin (``"ipopt"``, ``"sqpmethod"``, ``"fatrop"``, …), a cvxpy solver name
    (``"clarabel"``, ``"piqp"``, …) or a direct solver (``"clarabel"``, ``"piqp"``), ``None``
    for the backend's default; ``options``: solver options
    (added to the backend's defaults); ``retries`` (CasADi only): the cold-start chain run
    after a failed solve as ``(solver, option overrides)`` pairs, ``None`` for the backend's
    default chain and ``()`` for none; ``name``: a label shown in errors and traces;
    ``budget``: a :class:`Budget` set by :meth:`with_budget` (its options are in ``options``).
    """

    backend: str = "casadi"
    solver: str | None = None
    options: Mapping[str, Any] = field(default_factory=lambda: _frozen(None), compare=False)
    retries: tuple[tuple[str, Mapping[str, Any]], ...] | None = field(default=None,
                                                                      compare=False)
    name: str = "custom"
    #: a bound on each solve (:meth:`with_budget`), ``None`` for none
    budget: Budget | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        if not isinstance(self.backend, str) or self.backend not in BACKEND_NAMES:
            raise SolverError(f"Target: unknown backend {self.backend!r}; use one of "
                              f"{', '.join(BACKEND_NAMES)}")
        if self.solver is not None and not isinstance(self.solver, str):
            raise SolverError(f"Target({self.name}): solver must be a name (str) or None, got "
                              f"{type(self.solver).__name__}")
        if not isinstance(self.options, Mapping):
            raise SolverError(f"Target({self.name}): options must be a dict, got "
                              f"{type(self.options).__name__}")
        object.__setattr__(self, "options", _frozen(self.options))
        if self.retries is not None:
            ok = isinstance(self.retries, list | tuple) and all(
                isinstance(r, tuple | list) and len(r) == 2 and isinstance(r[0], str)
                and isinstance(r[1], Mapping) for r in self.retries)
            if not ok:
                raise SolverError(f"Target({self.name}): retries must be a list of (solver "
                                  f"name, options dict) pairs or None, got "
                                  f"{self.retries!r:.60}")
            if self.backend == "auto" and self.retries is not None:
                raise SolverError(f"Target({self.name}): the auto target picks its backend; "
                                  "name one ('exact', 'fast-convex') to pass retries")
            if self.backend != "casadi" and self.retries:
                raise SolverError(f"Target({self.name}): retry chains are a CasADi feature; "
                                  f"the {self.backend} backend has its own status checks")
            object.__setattr__(self, "retries",
                               tuple((s, _frozen(o)) for s, o in self.retries))
        if self.budget is not None and not isinstance(self.budget, Budget):
            raise SolverError(f"Target({self.name}): budget must be a Budget or None, got "
                              f"{type(self.budget).__name__}")
        if self.budget is not None and self.backend != "casadi":
            raise SolverError(f"Target({self.name}): budgets are for the CasADi NLP solvers; "
                              f"the {self.backend} backend would ignore it")

    # -- derived targets ------------------------------------------------------------
    def with_options(self, options: Mapping[str, Any] | None = None, /,
                     **more: Any) -> Target:
        """A copy with ``options`` (and keyword options) added to this target's; an option
        that imposes the target's budget cannot be changed here (use :meth:`with_budget`):
        the budget would then say one bound and the solver run another."""
        added = {**(options or {}), **more}
        if self.budget is not None:
            owned = self.budget.options(self.nlp_solver)
            clash = [k for k in added if k in owned and added[k] != owned[k]]
            if clash:
                raise SolverError(f"Target({self.name}).with_options: {clash[0]!r} is set by "
                                  f"the budget {self.budget} ({owned[clash[0]]!r}); change it "
                                  f"with with_budget")
        return replace(self, options={**self.options, **added}, name=f"{self.name}+options")

    def is_preset(self) -> bool:
        """Whether this target is the preset of its name itself (:data:`PRESETS`): every
        field equal, options, retries and budget included (``==`` leaves those out), so a
        user's target that only borrows a preset's name is not one."""
        preset = PRESETS.get(self.name)
        if preset is None:
            return False

        def fields(t: Target) -> tuple:
            retries = None if t.retries is None else tuple((s, _plain(o)) for s, o in t.retries)
            return t.backend, t.solver, _plain(t.options), retries, t.budget

        return fields(self) == fields(preset)

    def with_retries(self, retries: list[tuple[str, Mapping]] | tuple | None) -> Target:
        """A copy with another retry chain (``()`` for none, ``None`` for the default)."""
        return replace(self, retries=None if retries is None else tuple(retries))

    def with_budget(self, iterations: int | None = None,
                    seconds: float | None = None) -> Target:
        """A copy whose solves stop after ``iterations`` solver iterations and/or ``seconds``
        of wall-clock time (IPOPT only), reported as truncated (status ``max_iterations``,
        ``Solution.truncated``), never as optimal. The copy has no retry chain: a retry
        would break the time bound (add one back with :meth:`with_retries`; the backend
        still runs none after a stop by the budget). CasADi targets only."""
        if self.backend != "casadi":
            raise SolverError(f"Target({self.name}).with_budget: budgets are for the CasADi "
                              f"NLP solvers, not the {self.backend} backend")
        budget = Budget(iterations, seconds)
        return replace(self, options={**self.options, **budget.options(self.nlp_solver)},
                       retries=(), budget=budget, name=f"{self.name}+budget")

    def with_solver(self, solver: str | None) -> Target:
        """A copy that uses ``solver`` on the same backend (options are kept; a budget is
        carried over in the new solver's option names, or refused if it has none)."""
        other = replace(self, solver=solver, name=f"{self.backend}:{solver}")
        if self.budget is None:
            return other
        stale = set(BUDGET_OPTIONS.get(self.nlp_solver, {}).values()) | set(
            BUDGET_COMPANIONS.get(self.nlp_solver, {}))
        options = {k: v for k, v in self.options.items() if k not in stale}
        return replace(other, options={**options, **self.budget.options(other.nlp_solver)})

    # -- what the backends read ---------------------------------------------------------
    @property
    def nlp_solver(self) -> str | None:
        """The CasADi NLP solver this target runs (the backend's default when ``solver`` is
        ``None``); for a cvxpy target its ``solver`` as given (``None``: cvxpy picks per
        problem class)."""
        if self.backend != "casadi":
            return self.solver
        return self.solver or _CASADI_DEFAULT_SOLVER

    def solver_options(self) -> dict[str, Any]:
        """The options as a plain (mutable, deep-copied) dict for the backend."""
        return _plain(self.options)

    def retry_chain(self) -> list[tuple[str, dict]] | None:
        """The retry chain as plain ``(solver, options)`` pairs, or ``None`` (default)."""
        if self.retries is None:
            return None
        return [(s, _plain(o)) for s, o in self.retries]

    def emit_reason(self, allow_external: bool = False) -> str | None:
        """Why problems compiled for this target cannot be emitted as C, or ``None`` if
        they can: CasADi ``sqpmethod`` with a self-contained QP solver, or (with
        ``allow_external``) a solver whose C links an external library
        (:mod:`balustrade.backends.emittable`)."""
        from balustrade.backends.emittable import codegen_reason, full_options

        if self.backend != "casadi":
            return (f"target {self.name!r}: only problems compiled on the CasADi backend can "
                    f"be emitted as C")
        solver = self.nlp_solver
        reason = codegen_reason(solver, full_options(solver, self.options), allow_external)
        return None if reason is None else f"target {self.name!r}: {reason}"

    @property
    def can_emit(self) -> bool:
        """Whether problems compiled for this target can be emitted as self-contained C."""
        return self.emit_reason() is None

    def c_libraries(self) -> tuple[str, ...]:
        """The libraries the C emitted for this target links with (empty: only libm)."""
        from balustrade.backends.emittable import c_libraries, full_options

        if self.backend != "casadi":
            return ()
        solver = self.nlp_solver
        return c_libraries(solver, full_options(solver, self.options))

    def __reduce__(self) -> tuple:
        """Pickle as plain data (the read-only option views do not pickle): targets travel
        to sampling workers (:mod:`balustrade.learn.executors`)."""
        retries = None if self.retries is None else tuple(
            (s, _plain(o)) for s, o in self.retries)
        return (Target, (self.backend, self.solver, _plain(self.options), retries, self.name,
                         self.budget))

    def __str__(self) -> str:
        return f"{self.name} ({self.backend}{':' + self.solver if self.solver else ''})"


#: the largest dense constraint matrix (``m · n`` entries of the lowered LP/QP) that the
#: preset ``"fast-convex-sized"`` hands to DAQP: the DAQP engine's own limit
#: (:data:`balustrade.backends.daqp_engine.DENSE_LIMIT`, checked equal in the tests). 3-mass
#: (4.5) is far below it (DAQP several times faster than PIQP), 8-mass (4.5) far above
#: (DAQP 4x slower than row generation on PIQP; docs/adaptive.md, session 14)
SIZED_DENSE_LIMIT = 2_000_000

#: IPOPT's warm-start options (sampling paths, :mod:`balustrade.learn.sampler`)
_IPOPT_WARM = {"ipopt.warm_start_init_point": "yes", "ipopt.warm_start_bound_push": 1e-9,
               "ipopt.warm_start_mult_bound_push": 1e-9,
               "ipopt.warm_start_slack_bound_push": 1e-9, "ipopt.mu_init": 1e-6}
# The slack costs carry α_f = 1e6: IPOPT's scaled complementarity test would stop with
# α_f ξ_N ≈ 4e-6 at states of S_PB (above tol = 1e-6); demand absolute complementarity.
_IPOPT_SAMPLING = {"ipopt.compl_inf_tol": 1e-12}

# "convex-qp": DAQP needs a positive definite Hessian unless its proximal-point iterations
# are on (eps_prox > 0; they converge to the exact minimizer). Measured on the RAPSF QP (4.5)
# of the 3-mass chain (1440 tube rows), 40 closed-loop steps: with DAQP's default
# tolerances (1e-6) sqpmethod (tol_pr 1e-9) never converged (26 failures); primal/dual
# tolerances 1e-12 and eps_prox 1e-6: 5 failures; eps_prox 1e-9: more; eps_prox 1e-3: none.
# iter_limit 5000 (the default 1000 stopped at x = 0).
_CONVEX_QP = {"qpsol": "daqp",
              "qpsol_options": {"daqp": {"eps_prox": 1e-3, "iter_limit": 5000,
                                         "primal_tol": 1e-12, "dual_tol": 1e-12},
                                "error_on_fail": False}}
_CONVEX_QP_RETRIES = (("sqpmethod", {"convexify_strategy": "eigen-reflect"}),)

# "robust-sqp": the compact lowering (casadi_backend.LOWERINGS), the NLP the emitters generate
# the C from (codegen.emit.EMIT_LOWERING), so Python and its C solve the same NLP with the
# same chain. Why (issue #14/#16, "C = Python"): on the lane change (converging, seed 0,
# step 0) the expanded and the compact NLP are equal in exact arithmetic, but their rounding
# differs, and the failing SQP attempts of the cold (5.15) diverge differently: in Python
# (expanded) the eigen-reflect retry ran to 1e23 and IPOPT answered, in C (compact) that
# retry converged (both within tolerance, h_r 1.6983296861 vs 1.6983294591); the inputs then
# differed by 2.1e-6 (5.2) and 7.9e-6 (6.4). On the compact lowering in Python the same
# attempt answers at every step and the inputs agree to 1e-15 (tests/test_lane_c_chain.py).
_ROBUST_SQP = {"max_iter": 500, "lowering": "as-emitted"}

# Every other preset whose C the emitters generate from the compact lowering (sqpmethod in
# the layout's order: "fast-sqp", "fast-sqp-noretry", "convex-qp", "real-time") solves that
# lowering in Python too (issue #14, session 12), for the reason of _ROBUST_SQP: Python and
# its C then solve the same NLP, rounding included. The stage-ordered presets
# ("structured-ip", "structured-sqp") keep the expanded NLP in stage order in Python (the
# compact one is refused there); their C is the compact lowering permuted into stage
# order, measured equal to Python to the last bit (docs/engines.md). The value "as-emitted"
# (casadi_backend.AS_EMITTED) says exactly that: compact in the layout's order, expanded when
# a user's variant of these presets is stage-ordered (qpsol hpipm, solver fatrop), which
# then compiles as it did before session 12 instead of being refused.
_COMPACT = {"lowering": "as-emitted"}
# The stage-ordered presets whose C the emitters generate ("structured-ip",
# "structured-ip-noretry", "structured-sqp") carry "as-emitted" too: their lowering stays
# the expanded NLP in stage order (what "as-emitted" means for them), and their retries on
# another plugin (IPOPT) stop as that plugin's emitted C does (casadi_backend.
# EMITTED_STOP_OPTIONS; session 13 review: without it Python's IPOPT retry of
# "structured-ip" could stop at its acceptable level where the C's goes on).
_STAGED = {"lowering": "as-emitted"}

PRESETS: dict[str, Target] = {t.name: t for t in (
    Target("casadi", "ipopt", name="exact"),
    Target("casadi", "sqpmethod", _COMPACT, name="fast-sqp"),
    Target("casadi", "sqpmethod", _COMPACT, retries=(), name="fast-sqp-noretry"),
    Target("casadi", "sqpmethod", _ROBUST_SQP, name="robust-sqp"),
    Target("casadi", "sqpmethod", {**_CONVEX_QP, **_COMPACT}, retries=_CONVEX_QP_RETRIES,
           name="convex-qp"),
    Target("casadi", "ipopt", {"ipopt.mu_strategy": "adaptive"}, name="long-horizon"),
    Target("casadi", "ipopt", _IPOPT_SAMPLING, name="sampling-cold"),
    Target("casadi", "ipopt", {**_IPOPT_SAMPLING, **_IPOPT_WARM}, name="sampling-warm"),
    Target("casadi", "fatrop", _STAGED, retries=(("fatrop", {}), ("ipopt", {})),
           name="structured-ip"),
    Target("casadi", "fatrop", _STAGED, retries=(), name="structured-ip-noretry"),
    Target("casadi", "sqpmethod", {"qpsol": "hpipm", **_STAGED}, name="structured-sqp"),
    Target("cvxpy", None, name="cvxpy"),
    Target("cvxpy", "clarabel", name="conic"),
    Target("cvxpy", "clarabel", name="sdp"),
    # -- real-time mode (issue #14 §5) --
    replace(Target("casadi", "sqpmethod", _COMPACT).with_budget(
        iterations=REALTIME_ITERATIONS),
            name="real-time"),
    Target("direct", None, name="fast-convex"),
    Target("direct", "clarabel", name="fast-convex-conic"),
    Target("direct", "piqp", name="fast-convex-qp"),
    # row generation over the OCP's grouped rows (backends/row_generation.py; session 12);
    # the reduced QPs (few rows, 587 variables for 8 masses) condensed onto the variables:
    # 1.5x faster than the plain LDLᵀ on the recorded 8-mass reduced QPs, same objective;
    # without PIQP's Ruiz equilibration (session 15): set-up and update 0.6 ms cheaper each,
    # no more iterations, median 8-mass step 1.0 ms less CPU; one row per violated group and
    # round instead of 3: the same rounds, fewer rows, 8-10 % less CPU per step (session 15,
    # docs/adaptive.md)
    Target("direct", "piqp",
           {"row_generation": {"per_round": 1,
                               "reduced_options": {"kkt_solver": "sparse_ldlt_ineq_cond",
                                                   "preconditioner_iter": 0}}},
           name="fast-convex-rowgen"),
    # a hot-started dense active-set QP (backends/daqp_engine.py; session 14): 3-mass (4.5)
    # solves several times faster than PIQP with the same answers (docs/adaptive.md)
    Target("direct", "daqp", name="fast-convex-daqp"),
    # the size rule (backends/direct_backend.py, DENSE_CHOICE; session 14): DAQP as above on
    # LPs/QPs up to the DAQP engine's dense limit (daqp_engine.DENSE_LIMIT), PIQP beyond;
    # RAPSF's default (3 masses: DAQP, 8 masses: row generation on PIQP)
    Target("direct", None, {"daqp_max_entries": SIZED_DENSE_LIMIT}, name="fast-convex-sized"),
    # the lead of a recovery step (backends/recovery.py): the chain's interior-point retry
    # ("ipopt", {}), matched by solver and options, so the C runs the same attempt
    Target("casadi", "ipopt", name="recovery"),
    Target("auto", None, name="auto"),
)}

#: the solver-named spellings of presets (kept so that existing scripts resolve)
ALIASES: dict[str, str] = {"exact-ipopt": "exact", "ipopt-adaptive": "long-horizon",
                           "ipopt-sampling": "sampling-cold", "ipopt-warm": "sampling-warm",
                           "clarabel": "conic"}

#: warm-started sampling (Algorithm 7.6, :func:`sampling_targets`): for a target name, the
#: target of the warm solves along a path and that of the cold twin, which does the first
#: point of a path and redoes a warm solve that failed. The warm SQP runs without retries
#: (its cold twin is the retry).
SAMPLING_PAIRS: dict[str, tuple[str, str]] = {
    "fast-sqp": ("fast-sqp-noretry", "sampling-cold"),
    "exact": ("sampling-warm", "sampling-cold"),
}

#: what a bare backend name means where a target is expected
_BACKEND_DEFAULTS = {"casadi": "exact", "cvxpy": "cvxpy", "direct": "fast-convex", **ALIASES}


def target(spec: Target | str | None = None, *, default: Target | str = "exact",
           solver: str | None = None, options: Mapping[str, Any] | None = None,
           retries: list | tuple | None = None) -> Target:
    """Resolve ``spec`` to a :class:`Target`.

    ``spec`` is a target, a preset name (:data:`PRESETS`, or one of its :data:`ALIASES`), a
    backend name (``"casadi"`` → ``"exact"``, ``"cvxpy"`` → ``"cvxpy"``), or ``None`` for
    ``default``.
    ``solver``/``options``/``retries``, when given, override the resolved target's: options
    are added to its own, except that another ``solver`` starts from the backend's defaults
    (the resolved options and retries belong to its solver), so
    ``target("exact", solver="sqpmethod")`` is a CasADi sqpmethod target with the backend's
    defaults and no IPOPT options."""
    if spec is None:
        spec = default
    if isinstance(spec, str):
        name = _BACKEND_DEFAULTS.get(spec, spec)
        if name not in PRESETS:
            raise SolverError(f"unknown backend {spec!r} (nor a target preset); use a Target, "
                              f"a backend ({', '.join(BACKEND_NAMES)}) or a preset "
                              f"({', '.join(PRESETS)})")
        resolved = PRESETS[name]
    elif isinstance(spec, Target):
        resolved = spec
    else:
        raise SolverError(f"expected a Target, a preset name or a backend name, got "
                          f"{type(spec).__name__}")
    if solver is not None and solver != resolved.solver:
        resolved = Target(resolved.backend, solver, options or {},
                          None if retries is None else tuple(retries),
                          name=f"{resolved.backend}:{solver}")
        return resolved
    if options:
        resolved = resolved.with_options(options)
    if retries is not None:
        resolved = resolved.with_retries(retries)
    return resolved


def companion(spec: Target | str | None, main: Target | str) -> Target:
    """The target of a controller's second problem: ``spec`` when given, else ``"exact"``
    when ``main`` (the target of its first problem) is a CasADi target and ``main`` itself
    otherwise — so ``target="cvxpy"`` alone moves both problems to cvxpy, while on CasADi the
    slack problems (5.15) keep IPOPT (the SQP needs hundreds of iterations on them)."""
    if spec is not None:
        return target(spec)
    main = target(main)
    return PRESETS["exact"] if main.backend == "casadi" else main


def sampling_targets(spec: Target | str) -> tuple[Target, Target | None]:
    """The targets of warm-started sampling for ``spec``: ``(warm, cold twin)`` from
    :data:`SAMPLING_PAIRS` for the names listed there (``"fast-sqp"``: warm SQP without
    retries, cold IPOPT demanding absolute complementarity; ``"exact"``: IPOPT with its
    warm-start options, the same cold twin), ``(target(spec), None)`` for any other target
    (one compiled problem for warm and cold solves)."""
    name = ALIASES.get(spec, spec) if isinstance(spec, str) else None
    if name in SAMPLING_PAIRS:
        warm, cold = SAMPLING_PAIRS[name]
        return PRESETS[warm], PRESETS[cold]
    return target(spec), None


__all__ = ["ALIASES", "BACKEND_NAMES", "BUDGET_COMPANIONS", "BUDGET_OPTIONS", "PRESETS",
           "REALTIME_ITERATIONS", "SAMPLING_PAIRS", "SIZED_DENSE_LIMIT", "Budget", "Target",
           "companion", "sampling_targets", "target"]
