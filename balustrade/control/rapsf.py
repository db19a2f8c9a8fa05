"""Algorithm 4.1: the robust adaptive predictive safety filter with homothetic tubes (thesis
Chapter 4, SPEC §2.21, with Remark 4.6 as an option).

Per step: update ``Θ_k`` with the estimator (``k >= 1``), solve (4.5)
(:func:`balustrade.problems.rapsf.rapsf_problem`) at ``(x_k, Θ_k)`` and apply
``u_k = K x_k + v*_0``, storing the plan and setting ``k_inf = 0``. Otherwise
(``k_inf ← k_inf + 1``):

* ``k_inf <= N − 1`` and a stored plan: with ``shrinking=True`` (Remark 4.6) first solve (4.5)
  with the horizon ``N − k_inf`` and apply its ``K x_k + v*_0`` (``"shrunk_horizon"``);
  otherwise, or if that fails, the stored plan with tube feedback on the current state,
  ``K x_k + v*_{k_inf | k − k_inf}`` (``"stored_plan"``);
* else the backup policy ``π_Cf(x, u_p, k)`` (``"backup"``; default ``K x``, safe on the §4.7
  terminal set ``z = 0, α <= 1``, i.e. on ``𝕏₀``; or an affine law ``(K_b, k_b)``, a
  ``casadi.Function`` of ``x`` — both emitted as C — or a Python callable:
  :mod:`balustrade.control.rapsf_backup`).

``k_inf`` starts at ``N − 1``, so a state in ``C_f \\ F_feas(Θ₀)`` uses the backup at once.
Only a solve that ended ``optimal`` is used; any other status is recorded in
``StepInfo.uncertified`` and handled as infeasible.

Parameter-set updates (Assumption 4.2): any ``estimator`` with
``update(x_prev, u_prev, x) -> Θ`` (a :class:`~balustrade.dsl.sets.Polytope`; e.g. the
set-membership estimators of :mod:`balustrade.estimate`). A new set is accepted only if it is
nested in the current one (its vertices inside ``Θ_{k−1}``; else ``"theta_not_nested"`` and
``Θ_{k−1}`` is kept). An estimator that raises :class:`~balustrade.errors.EmptySetError`,
returns ``None`` or records the status ``"falsified"`` as the last entry of its ``history``
(:class:`balustrade.estimate.SetEstimator`) has falsified every model in ``Θ``: the status
``"model_falsified"`` is recorded and the backup policy is applied from then on. A
:class:`~balustrade.estimate.SetEstimator` decides "empty" with a certificate and records it;
an :class:`~balustrade.errors.EmptySetError` escaping one is not such a verdict: the step
records ``"theta_update_failed"`` and keeps ``Θ_{k−1}``.

An estimator that returns the current set itself (e.g. :class:`~balustrade.estimate.BoxUpdate`
when ``Θ_{k−1} ⊆ Δ_k``) costs nothing more: ``Θ_k`` and ``s_jr`` are kept. With the vertices
of ``𝕏₀`` enumerated (small ``n``), ``s_jr`` of a new ``Θ_k`` is one tensor product over the
affine form of ``A_cl(θ)``.

Vertex data (``vertex_data``): with ``"parameters"`` (the default) the vertices of ``Θ_k``
and the constants ``s_jr`` are parameters of one compiled problem per horizon on every target
— CasADi, and the convex targets (``"cvxpy"``, ``"fast-convex"``, ``"auto"``), whose lowering
keeps the rows ``H_X A_cl(θ^j) z_i + α_i s_j`` as a constraint matrix affine in the parameters
and only updates its values — so a new ``Θ_k`` never recompiles (fewer vertices than compiled
are padded by repetition). With ``"constants"`` the vertex data are numbers in the problem,
which is recompiled whenever the vertices change.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import numpy as np

from balustrade._checks import as_matrix, as_vector, check_horizon, check_instance
from balustrade.backends import Solution, compile, resolve_target
from balustrade.backends.lp import verified_supports
from balustrade.control.base import StepInfo, note_solve, outcome
from balustrade.control.deploy import RAPSFDeployment
from balustrade.control.rapsf_backup import backup_policy
from balustrade.control.rapsf_enlarge import TerminalEnlargement
from balustrade.control.rapsf_supports import LearnedSupports
from balustrade.dsl.sets import Polytope
from balustrade.errors import BalustradeError, EmptySetError
from balustrade.estimate.base import SetEstimator
from balustrade.problems.rapsf import (
    TerminalSet,
    check_parametric_system,
    check_terminal,
    check_tube_sets,
    closed_loop_matrices,
    rapsf_problem,
    row_dependence,
    rows_shared,
    s_constants,
    shared_rows,
    tube_constants,
    unit_polytope,
)

Backup = Callable[[np.ndarray, np.ndarray, int], np.ndarray]



#: the targets whose (4.5) keeps every tube row because Algorithm 4.1's C is emitted from
#: them (:data:`balustrade.codegen.emit_rapsf.EMITTABLE_TARGET`)
EMITTED_TARGETS = ("convex-qp",)

#: (4.5) with at least this many grouped tube rows (4.5c) is solved by row generation
#: (``"fast-convex-rowgen"``, exact) when the target is ``fast-convex``/``fast-convex-qp``/
#: ``auto``: measured 8–10x faster on 8 masses (28644 rows), slower on 3 masses (590 rows:
#: 1.96 against 1.59 ms per solve; docs/adaptive.md, session 12). Only the presets
#: themselves qualify (name and options: a user's Target named like one keeps its own
#: options); ``RAPSF(..., row_generation=False)`` turns it off.
ROWGEN_MIN_ROWS = 10000
ROWGEN_FROM = ("fast-convex", "fast-convex-qp", "fast-convex-sized", "auto")

#: the target of ``RAPSF(...)`` without ``target=`` (session 14, issue #15): the direct
#: backend choosing its QP engine by the size of the lowered (4.5) — a hot-started dense
#: active-set engine when small (3 masses: 0.75 vs 2.03 ms per closed-loop step,
#: docs/adaptive.md "Session 14: the default"), else the sparse interior-point engine, and row
#: generation from :data:`ROWGEN_MIN_ROWS` tube rows (8 masses); the preset names the
#: solvers (backends/targets.py). :attr:`RAPSF.engine` and
#: ``info.solutions["rapsf"].solver`` say which ran.
DEFAULT_TARGET = "fast-convex-sized"


class RAPSF:
    """Algorithm 4.1 (SPEC §2.21) as a controller: ``step(x, u_p) -> (u, StepInfo)``.

    ``system`` is affine in θ (``A0, A_list, B0, B_list``); ``X0`` the tube shape
    ``𝕏₀ = {H_X x <= h}`` (``h > 0``), ``(F, G)`` the joint constraints ``Fx + Gu <= 1``,
    ``W`` the disturbance polytope, ``K`` the tube gain, ``Theta0`` the initial parameter
    set; with the default terminal set, ``X0`` must satisfy Assumption 4.11 for ``Θ₀``
    (checked by LPs, else :class:`~balustrade.errors.BalustradeError`). ``values`` of each
    step: ``k_inf``, ``objective`` (of an optimal solve), ``n_vertices`` (of ``Θ_k``).
    ``vertex_data``: ``"parameters"`` (one compile per horizon) or ``"constants"`` (recompiled
    when ``Θ_k`` changes), see the module docstring.

    ``enlarge=True`` (or a :class:`~balustrade.control.rapsf_enlarge.TerminalEnlargement`)
    enlarges the terminal set online (Theorem 4.12, Remark 4.13, SPEC §2.22): every optimal
    solve adds its tube pairs (and zero-dilation points) to the generators of a hull that
    replaces (4.5e); ``terminal_set`` is the set in use, ``values["n_generators"]`` its size.
    With ``vertex_data="parameters"`` the generators are a parameter of fixed ``capacity``
    (no recompile, on every target); with ``"constants"`` the problem is recompiled when they
    change.

    ``warm_start=True`` starts (4.5) from the previous step's solution after a step that
    solved it optimally (``k_inf == 0``, same compiled problem), else cold; the emitted C
    follows the same rule (``<name>_WARM_START``), so C = Python holds with it. It takes
    effect on targets that accept a starting point (the CasADi ones, e.g. ``"convex-qp"``,
    where it shortened the C step several-fold, docs/adaptive.md); ``"fast-convex"``
    ignores it. The inputs equal the cold ones only within the solver's accuracy.

    ``target`` (default :data:`DEFAULT_TARGET`, ``"fast-convex-sized"``: the direct backend
    with a hot-started dense active-set engine for small (4.5), the sparse interior-point one
    for large, row generation from :data:`ROWGEN_MIN_ROWS` rows; session 14. Before it,
    ``"fast-convex"``, the interior-point engine only, session 13): (4.5)
    is a QP, and on it ``"exact"`` (the NLP target) gave the same inputs (3 masses: within 3.8e-11
    over 30 closed-loop steps, the same fallbacks) at 27 ms against 2.0 ms per step; on 8
    masses (where ``"fast-convex"`` becomes row generation, below) 6–22 s against 12–69 ms,
    and ``"exact"`` stopped ``optimal_inaccurate`` where the QP path solved;
    docs/adaptive.md "Session 13: audit fixes". ``"convex-qp"`` is the target whose
    C is emitted (:meth:`deployment_spec`).

    ``row_generation=True`` solves (4.5) by row generation (preset ``"fast-convex-rowgen"``,
    the same answers) when ``target`` is one of the presets :data:`ROWGEN_FROM` unchanged and
    the problem has :data:`ROWGEN_MIN_ROWS` grouped tube rows or more; ``False``: always
    ``target``. Setting the attribute later drops the problems compiled so far."""

    def __init__(self, system: object, X0: Polytope, F: np.ndarray, G: np.ndarray,
                 W: Polytope, K: np.ndarray, N: int, Theta0: Polytope,
                 estimator: object | None = None, backup: Backup | object | None = None,
                 target: object = DEFAULT_TARGET, shrinking: bool = False,
                 terminal: TerminalSet | None = None, tol: float = 1e-7,
                 enlarge: bool | TerminalEnlargement = False, name: str = "rapsf",
                 vertex_data: str = "parameters", warm_start: bool = False,
                 row_generation: bool = True):
        self.n, self.m, self.q = check_parametric_system(system, name)
        self.N = check_horizon(N, name)
        self.K = as_matrix(K, f"{name}: K", (self.m, self.n))
        check_instance(Theta0, Polytope, f"{name}: Theta0")
        if Theta0.dim != self.q:
            raise BalustradeError(f"{name}: Theta0 has dimension {Theta0.dim}, the system "
                                  f"has q = {self.q} parameters")
        check_tube_sets(system, X0, W, name)       # before any support LP
        check_terminal(terminal, self.n, name)      # not only at the first solve
        if estimator is not None and not callable(getattr(estimator, "update", None)):
            raise BalustradeError(f"{name}: estimator must have a method "
                                  "update(x_prev, u_prev, x) -> Θ")
        self.system, self.X0, self.F, self.G, self.W = system, X0, F, G, W
        self.Theta0, self.estimator, self.terminal, self.name = Theta0, estimator, terminal, name
        self.default_backup = backup is None        # π_Cf: None, (K_b, k_b), Function, callable
        self.backup, self.backup_law = backup_policy(backup, self.n, self.m, self.K, name)
        self.shrinking = bool(shrinking)
        if not isinstance(warm_start, bool):
            raise BalustradeError(f"{name}: warm_start must be a bool, got "
                                  f"{type(warm_start).__name__}")
        self.warm_start = warm_start
        if not isinstance(row_generation, bool):
            raise BalustradeError(f"{name}: row_generation must be a bool, got "
                                  f"{type(row_generation).__name__}")
        self.target = resolve_target(target)
        if warm_start and self.target.backend != "casadi":
            warnings.warn(f"{name}: warm_start=True has no effect on the target "
                          f"{self.target.name!r} (it takes no starting point); use a CasADi "
                          "target such as 'convex-qp' for warm starts", stacklevel=2)
        if vertex_data not in ("parameters", "constants"):
            raise BalustradeError(f"{name}: vertex_data must be 'parameters' or 'constants', "
                                  f"got {vertex_data!r}")
        self.parametric = vertex_data == "parameters"
        self._n_compiled = len(Theta0.vertices())
        self._dependence = row_dependence(system, X0)
        # the target Algorithm 4.1's C is emitted from (the C step takes any vertex data, so
        # it keeps every row) solves the same problem in Python: C = Python (emit_rapsf,
        # deployment_spec). Since interior-point NLP targets emit C too (linking their
        # library), "emits C" no longer singles it out: the QP path is named.
        self._share = self.target.name not in EMITTED_TARGETS
        self._row_generation = row_generation  # allowed where it pays (_target_for)
        self._shared: dict[int, np.ndarray | None] = {}
        self._X0_vertices = _small_vertices(X0)
        self._s_affine = _s_affine(system, X0, self.K, self._X0_vertices)
        self._s_l1 = None if self._s_affine is not None else _s_l1(system, X0, self.K)
        #: the vertices of 𝕏₀ the s_jr LPs ended at (created at the first use)
        self._learned: LearnedSupports | None = None
        self._compiled: dict = {}
        self._engine: str | None = None     # the solver of the last full-horizon (4.5)
        if terminal is None or terminal.H_T is None:
            self._check_default_terminal(tol)
        self.enlargement = _enlargement(enlarge, self.n, terminal, self._X0_vertices, name)
        self.reset()

    def _check_default_terminal(self, tol: float) -> None:
        """The §4.7 terminal set ``z = 0, 0 <= α <= 1`` needs ``A_cl(θ^j)𝕏₀ ⊕ W ⊆ 𝕏₀`` at
        every vertex of ``Θ₀`` and ``(x, Kx) ∈ 𝒵`` on ``𝕏₀`` (Assumption 4.11, SPEC §2.20):
        ``s_jr + w̄_r <= 1`` and ``t_r <= 1``; otherwise the guarantee is void, so refuse."""
        c = tube_constants(self.X0, self.W, self.system, self.K, self.Theta0.vertices(),
                           self.F, self.G)
        rpi, cons = float(np.max(c.s + c.w_bar[:, None])), float(np.max(c.t))
        if rpi > 1 + tol:
            raise BalustradeError(f"{self.name}: X0 is not robustly invariant for K and W at "
                                  f"the vertices of Theta0 (max_jr s_jr + w̄_r = {rpi:.4g} > 1):"
                                  " the terminal set z = 0, α <= 1 is not safe (Assumption "
                                  "4.11; see balustrade.design.rapsf.contractive_polytope)")
        if cons > 1 + tol:
            raise BalustradeError(f"{self.name}: (x, Kx) leaves 𝒵 on X0 (max_r t_r = "
                                  f"{cons:.4g} > 1): the terminal set z = 0, α <= 1 is not "
                                  "safe (Assumption 4.11)")

    def reset(self) -> None:
        """Back to ``k = 0``, ``Θ₀``, ``k_inf = N − 1`` and no stored plan (and the
        estimator's own ``reset`` when it has one)."""
        if callable(getattr(self.estimator, "reset", None)):
            self.estimator.reset()
        self.k = 0
        self.k_inf = self.N - 1
        self.plan: np.ndarray | None = None
        self.tube: tuple[np.ndarray, np.ndarray] | None = None   # (z, α) of the plan
        self._last: tuple[object, Solution] | None = None   # (compiled key, optimal solve)
        self.falsified = False
        self._set_theta(self.Theta0)
        self._prev: tuple[np.ndarray, np.ndarray] | None = None
        if self.enlargement is not None:               # its tubes are robust for Θ_k, not Θ₀
            self.enlargement.reset()

    @property
    def terminal_set(self) -> TerminalSet:
        """The terminal set (4.5e) currently in use: with ``enlarge`` the hull (4.10) of the
        recorded tube pairs and the base set (:class:`TerminalEnlargement`), else the given
        set (``TerminalSet()`` for the §4.7 default)."""
        if self.enlargement is not None:
            return self.enlargement.terminal_set
        return self.terminal if self.terminal is not None else TerminalSet()

    # -- Θ_k --------------------------------------------------------------------------------
    def _set_theta(self, Theta: Polytope, vertices: np.ndarray | None = None) -> None:
        """``Θ_k``, its vertices (``vertices`` when the caller enumerated them already: for
        a general polytope, e.g. :class:`~balustrade.estimate.ExactUpdate`'s, enumeration is
        most of the update) and ``s_jr``."""
        self.Theta = Theta
        self.vertices = np.atleast_2d(Theta.vertices() if vertices is None else vertices)
        if self._s_affine is not None:
            self._s = _s_from_affine(self._s_affine, self.vertices)
        elif self._s_l1 is not None:
            self._s = _s_from_l1(self._s_l1, self.vertices)
        else:
            if self._learned is None:
                self._learned = LearnedSupports(self.X0)
            self._s = _s_from_lps(self.X0, self.system, self.K, self.vertices,
                                  supports=self._learned)

    def _update_theta(self, x: np.ndarray, info: StepInfo) -> None:
        """Line 4 of Algorithm 4.1 with the nesting check of Assumption 4.2."""
        if self.estimator is None or self._prev is None or self.falsified:
            return
        if not np.all(np.isfinite(x)):              # no transition to learn from: Θ_k kept
            return
        try:
            new = self.estimator.update(self._prev[0], self._prev[1], x)
        except EmptySetError:
            if isinstance(self.estimator, SetEstimator):
                # its "empty" is certified and recorded as ``falsified`` in its history; an
                # EmptySetError escaping it (a set it builds) is not: Θ_{k−1} is kept
                info.status = "theta_update_failed"
                return
            new = None
        history = getattr(self.estimator, "history", None)
        if new is None or (history and str(getattr(history[-1], "status", "")) == "falsified"):
            self.falsified = True                   # Δ_k ∩ Θ_{k−1} = ∅: no θ explains x_k
            return
        if new is self.Theta:                       # the same set: Θ_k, s_jr unchanged
            return
        check_instance(new, Polytope, f"{self.name}: estimator.update result")
        vertices = np.atleast_2d(new.vertices())      # enumerated once: nesting and s_jr
        if not np.all(self.Theta.contains_many(vertices, tol=1e-9)):
            info.status = "theta_not_nested"
            return
        self._set_theta(new, vertices)

    # -- (4.5) ------------------------------------------------------------------------------
    def _shared_rows(self, n_th: int) -> np.ndarray | None:
        """Which rows of (4.5c) the compiled problem with ``n_th`` vertex columns shares
        between vertices (:func:`~balustrade.problems.rapsf.shared_rows` of ``Θ₀``'s vertices
        padded by repetition; ``None`` when no row is shared): a box ``Θ_k`` keeps the
        vertex order of ``Θ₀``, so the same rows coincide at every step, which
        :meth:`_solve` checks exactly before using that problem. ``None`` also on the target
        Algorithm 4.1's C is emitted from (:data:`EMITTED_TARGETS`: the C step accepts any
        vertex data, so it and the Python step keep every row); :meth:`deployment_spec` hands
        the C every row on any target."""
        if not self._share:
            return None
        if n_th not in self._shared:
            V0 = np.atleast_2d(self.Theta0.vertices())
            rep = shared_rows(self._dependence, V0[np.arange(n_th) % len(V0)].T)
            self._shared[n_th] = None if np.all(rep == np.arange(n_th)[None, :]) else rep
        return self._shared[n_th]

    def _data_share_rows(self, rep: np.ndarray, params: dict, n_th: int) -> bool:
        """:func:`~balustrade.problems.rapsf.rows_shared` for the current vertex data, checked
        again only when ``Θ_k`` (its vertex array or ``s_jr``, new objects on every change
        in :meth:`_set_theta`) changed; the cache holds the arrays themselves, so an
        identity test cannot be fooled by a reused address."""
        last = getattr(self, "_checked", None)
        if last is not None and last[0] is self.vertices and last[1] is self._s \
                and last[2] == n_th:
            return last[3]
        ok = rows_shared(rep, self._dependence, params["theta"], params["s"])
        self._checked = (self.vertices, self._s, n_th, ok)
        return ok

    def _solve(self, x: np.ndarray, u_p: np.ndarray, horizon: int) -> Solution:
        """(4.5) with ``horizon`` at ``(x, Θ_k)``; with ``warm_start`` the main horizon starts
        from the previous step's solution when that step solved it optimally (``k_inf ==
        0``) with the same compiled problem — the rule of the emitted C
        (``BAL_RAPSF_WARM_START``), so that C and Python start alike."""
        params = {"x0": x, "u_p": u_p}
        if self.parametric:
            n_th = max(self._n_compiled, len(self.vertices))
            idx = np.arange(n_th) % len(self.vertices)         # pad by repetition
            params["theta"] = self.vertices[idx].T
            params["s"] = self._s[:, idx]
            rep, key = self._shared_rows(n_th), (horizon, n_th)
            if rep is not None and not self._data_share_rows(rep, params, n_th):
                rep, key = None, (horizon, n_th, "all rows")  # these data repeat no rows
            if key not in self._compiled:
                ocp = self._problem(horizon, n_vertices=n_th, shared=rep)
                self._compiled[key] = compile(ocp, self._target_for(ocp))
            if self.enlargement is not None:
                params["terminal_generators"] = self.enlargement.padded()
        else:
            version = 0 if self.enlargement is None else self.enlargement.version
            key = (horizon, (self.vertices.tobytes(), version))
            if key not in self._compiled:
                self._compiled = {k: c for k, c in self._compiled.items()
                                  if k[1] == key[1]}               # keep the current Θ only
                ocp = self._problem(horizon, vertices=self.vertices)
                self._compiled[key] = compile(ocp, self._target_for(ocp))
        warm = None
        if self.warm_start and horizon == self.N and self.k_inf == 0 \
                and self._last is not None and self._last[0] == key:
            warm = self._last[1]
        compiled = self._compiled[key]
        if horizon == self.N:
            self._engine = getattr(compiled, "solver_name", None) or getattr(
                getattr(compiled, "target", None), "nlp_solver", None)
        sol = compiled.solve(params, warm_start=warm)
        if horizon == self.N:
            # the solver that answered (the fallback's, when the dense engine's answer failed
            # its KKT check)
            self._engine = getattr(sol, "solver", None) or self._engine
            self._last = (key, sol) if outcome(sol) == "optimal" else None
        return sol

    @property
    def row_generation(self) -> bool:
        """Whether (4.5) may be solved by row generation (:meth:`_target_for`)."""
        return self._row_generation

    @row_generation.setter
    def row_generation(self, value: bool) -> None:
        if not isinstance(value, bool):
            raise BalustradeError(f"{self.name}: row_generation must be a bool, got "
                                  f"{type(value).__name__}")
        if value != self._row_generation:
            self._compiled = {}     # compiled for the other choice
            self._last = None
        self._row_generation = value

    @property
    def engine(self) -> str | None:
        """The solver that answered the last (4.5) of full horizon solved (its
        ``Solution.solver``: the engine's name on the direct backend — the sparse engine's
        when the dense one fell back to it — the NLP solver's on CasADi): the choice of the
        size rule of the default target unless a fallback answered; ``None`` before the
        first step."""
        return self._engine

    def _target_for(self, ocp: object) -> object:
        """The target (4.5) is compiled for in :meth:`step`: ``fast-convex-rowgen`` in place
        of :attr:`target` when that is one of the presets :data:`ROWGEN_FROM` itself (name,
        backend, solver, options, retries and budget: a user's Target that only borrows the
        name keeps its own options) and the problem has :data:`ROWGEN_MIN_ROWS` grouped rows
        or more (the same answers), else :attr:`target`."""
        rows = sum(len(g) for g in getattr(ocp, "row_groups", {}).values())
        if self._row_generation and rows >= ROWGEN_MIN_ROWS \
                and self.target.name in ROWGEN_FROM and self.target.is_preset():
            return resolve_target("fast-convex-rowgen")
        return self.target

    def deployment_spec(self) -> RAPSFDeployment:
        """Algorithm 4.1 for :func:`balustrade.codegen.emit_rapsf` (one C call per step):
        (4.5) compiled as :meth:`step` compiles it (parametric vertex data, the same
        compiled object), and this controller as the ``host`` of the estimator."""
        if not self.parametric:
            raise BalustradeError(f"{self.name}: the C step takes the vertex data as "
                                  "parameters; build the controller with "
                                  "vertex_data='parameters' (and target='convex-qp')")
        n_th = max(self._n_compiled, len(self.vertices))
        horizons = {"main": self.N}
        if self.shrinking:                      # Remark 4.6: (4.5) with N − k_inf, k_inf >= 1
            horizons.update({f"shrunk{h}": h for h in range(1, self.N)})
        problems = {}
        for label, h in horizons.items():
            # every row: the C step cannot check that the vertex data repeat shared rows
            key = (h, n_th, "all rows") if self._share else (h, n_th)
            if key not in self._compiled:
                self._compiled[key] = compile(self._problem(h, n_vertices=n_th), self.target)
            problems[label] = self._compiled[key]
        return RAPSFDeployment(problems, "Algorithm 4.1, the RAPSF",
                               K=self.K, N=self.N, n_vertices=n_th,
                               shrinking=self.shrinking, default_backup=self.default_backup,
                               host=self)

    def shared_rows_problem(self) -> tuple[object, np.ndarray, np.ndarray] | None:
        """(4.5) with the horizon ``N`` and the rows of (4.5c) that coincide between the
        padded vertices written once, as :meth:`step` compiles and uses it when the vertex
        data repeat those rows: ``(compiled, rep, dependence)`` with the merge map ``rep``
        (``n_X × n_θ``, :func:`~balustrade.problems.rapsf.shared_rows`) and the rows'
        dependence on ``θ`` (``n_X × q``) for the check
        :func:`~balustrade.problems.rapsf.rows_shared`; ``None`` when no row is shared
        (or on a target whose C keeps every row). For the emitted C of the default target."""
        n_th = max(self._n_compiled, len(self.vertices))
        rep = self._shared_rows(n_th) if self.parametric else None
        if rep is None:
            return None
        key = (self.N, n_th)
        if key not in self._compiled:
            ocp = self._problem(self.N, n_vertices=n_th, shared=rep)
            self._compiled[key] = compile(ocp, self._target_for(ocp))
        return self._compiled[key], rep, np.asarray(self._dependence, dtype=bool)

    def _problem(self, horizon: int, **vertex_data: object) -> object:
        terminal = self.terminal
        if self.enlargement is not None:          # a parameter slot, or the current generators
            base = self.enlargement.base or TerminalSet()
            terminal = (base.slot(self.enlargement.capacity) if self.parametric
                        else self.enlargement.terminal_set)
        return rapsf_problem(self.system, self.X0, self.F, self.G, self.W, self.K, horizon,
                             terminal=terminal, X0_vertices=self._X0_vertices,
                             name=f"{self.name}_N{horizon}",
                             **vertex_data)

    # -- Algorithm 4.1 --------------------------------------------------------------------------
    def step(self, x: np.ndarray, u_p: np.ndarray) -> tuple[np.ndarray, StepInfo]:
        """One step of Algorithm 4.1; never raises for a failed solve."""
        # wrong sizes or non-numbers are errors; NaN/inf entries are handled below
        x = as_vector(x, f"{self.name}.step: x", self.n, finite=False)
        u_p = as_vector(u_p, f"{self.name}.step: u_p", self.m, finite=False)
        info = StepInfo()
        if not np.all(np.isfinite(u_p)):
            u_p = np.where(np.isfinite(u_p), u_p, 0.0)
            info.status = "non_finite_proposal"
        self._update_theta(x, info)
        info.values["n_vertices"] = float(len(self.vertices))
        u = self._decide(x, u_p, info)
        info.values["k_inf"] = float(self.k_inf)
        # a non-finite state starts no transition: the next update needs two measured states
        self._prev = (x, u) if np.all(np.isfinite(x)) else None
        self.k += 1
        return u, info

    def _decide(self, x: np.ndarray, u_p: np.ndarray, info: StepInfo) -> np.ndarray:
        if self.falsified or not np.all(np.isfinite(x)):
            info.status = "model_falsified" if self.falsified else "non_finite_state"
            info.fallback = "backup"
            return self._backup(x, u_p)
        sol = self._solve(x, u_p, self.N)
        info.solutions["rapsf"] = sol
        info.solve_time += float(getattr(sol, "solve_time", 0.0) or 0.0)
        if note_solve(info, "rapsf", outcome(sol)):
            self.plan = np.asarray(sol["v"], dtype=float).reshape(self.m, self.N)
            self.tube = _tube(sol, self.n, self.N)
            self.k_inf = 0
            info.values["objective"] = float(sol.objective)
            if self.enlargement is not None:                       # Theorem 4.12: record
                try:
                    self.enlargement.record(sol["z"], sol["alpha"])
                except BalustradeError:             # a pruning LP failed: keep the old set
                    info.status = "enlarge_failed"
                info.values["n_generators"] = float(self.enlargement.generators.shape[1])
            return self.K @ x + self.plan[:, 0]
        self.k_inf += 1
        if info.status == "ok":
            info.status = outcome(sol)
        if self.k_inf <= self.N - 1 and self.plan is not None:
            if self.shrinking:
                short = self._solve(x, u_p, self.N - self.k_inf)
                info.solutions["rapsf_shrunk"] = short
                if note_solve(info, "rapsf_shrunk", outcome(short)):
                    info.fallback = "shrunk_horizon"
                    self._store_shrunk(short)
                    return self.K @ x + self.plan[:, self.k_inf]
            info.fallback = "stored_plan"
            return self.K @ x + self.plan[:, self.k_inf]
        info.fallback = "backup"
        return self._backup(x, u_p)

    def _store_shrunk(self, short: Solution) -> None:
        """Remark 4.6: after an optimal (4.5) with the horizon ``N − k_inf`` at ``x_k`` the
        state follows *its* tube, so it becomes the stored plan from column ``k_inf`` on:
        ``plan[:, k_inf + i] = v̂_i`` and ``tube`` columns ``k_inf + i`` ``= (ẑ_i, α̂_i)``
        (``i = 0 … N − k_inf − 1`` for the plan, ``0 … N − k_inf`` for the tube).
        Its last set lies in ``C_f`` at the same time ``k − k_inf + N`` as the old plan's,
        so ``k_inf`` keeps counting from the last full solve and a later stored-plan
        fallback ``K x + plan[:, k_inf]`` (or the backup after ``N − 1``) keeps Theorem
        4.7's guarantee: ``x_{k+i}`` lies in the stored tube's set ``k_inf + i``. Without
        this the fallback would use the old plan, whose tube the state may have left
        (audit session 13, finding 1)."""
        h = self.N - self.k_inf
        self.plan = self.plan.copy()
        self.plan[:, self.k_inf:] = np.asarray(short["v"], dtype=float).reshape(self.m, h)
        if self.tube is not None:
            z, alpha = _tube(short, self.n, h)
            self.tube = (self.tube[0].copy(), self.tube[1].copy())
            self.tube[0][:, self.k_inf:] = z
            self.tube[1][self.k_inf:] = alpha

    def _backup(self, x: np.ndarray, u_p: np.ndarray) -> np.ndarray:
        x_safe = np.where(np.isfinite(x), x, 0.0)
        return np.asarray(self.backup(x_safe, u_p, self.k), dtype=float).reshape(self.m)


def _tube(sol: Solution, n: int, horizon: int) -> tuple[np.ndarray, np.ndarray] | None:
    """``(z, α)`` of an optimal (4.5) as ``(n × (horizon+1), horizon+1)`` arrays (the sets
    ``z_i ⊕ α_i 𝕏₀``), or ``None`` when the solution does not carry them."""
    try:
        z = np.asarray(sol["z"], dtype=float).reshape(n, horizon + 1)
        alpha = np.asarray(sol["alpha"], dtype=float).reshape(horizon + 1)
    except (BalustradeError, ValueError):
        return None
    return z, alpha


def _enlargement(enlarge: bool | TerminalEnlargement, n: int, terminal: TerminalSet | None,
                 X0_vertices: np.ndarray | None, name: str) -> TerminalEnlargement | None:
    """The ``enlarge`` option: ``False`` (none), ``True`` (a :class:`TerminalEnlargement`
    over ``terminal`` with zero-dilation points when the vertices of ``𝕏₀`` are known), or
    a user-built one (its ``n`` must match)."""
    if terminal is not None and terminal.has_generators and enlarge is not False:
        raise BalustradeError(f"{name}: enlarge needs an H-representation or the default as "
                              "terminal set (the generators are recorded online)")
    if isinstance(enlarge, TerminalEnlargement):
        if enlarge.n != n:
            raise BalustradeError(f"{name}: enlarge is for states of dimension {enlarge.n}, "
                                  f"the system has n = {n}")
        return enlarge
    if not isinstance(enlarge, bool):
        raise BalustradeError(f"{name}: enlarge must be a bool or a TerminalEnlargement, got "
                              f"{type(enlarge).__name__}")
    return TerminalEnlargement(n, terminal, X0_vertices) if enlarge else None


def _small_vertices(X0: Polytope, max_dim: int = 6) -> np.ndarray | None:
    """The vertices of ``𝕏₀`` when it is small enough to enumerate once (then ``s_jr`` is a
    matrix product per update instead of ``n_X · n_θ`` LPs); else ``None`` (LPs)."""
    if X0.dim > max_dim:
        return None
    try:
        return np.atleast_2d(X0.vertices())
    except BalustradeError:
        return None


def _s_affine(system: object, X0: Polytope, K: np.ndarray,
              X0_vertices: np.ndarray | None) -> np.ndarray | None:
    """``T[i] = H_X A_cl,i V_Xᵀ`` for ``A_cl(θ) = A_cl,0 + Σ_i θ_i A_cl,i`` (``A_cl,i = A_i +
    B_i K``, (4.6) is affine in θ) and the enumerated vertices ``V_X`` of ``𝕏₀``, stacked
    ``(q + 1, n_X, n_v)``: then ``s_jr = max_v (T[0] + Σ_i θ^j_i T[i])_rv`` (SPEC §2.20) is
    one small tensor product per new ``Θ_k`` (:func:`_s_from_affine`) instead of
    :func:`~balustrade.problems.rapsf.s_constants`' model matrices per vertex. ``None``
    without enumerated vertices (then ``s_constants`` solves its LPs)."""
    if X0_vertices is None:
        return None
    HX = unit_polytope(X0, "rapsf")
    V = np.asarray(X0_vertices, dtype=float).T
    return np.stack([HX @ P @ V for P in _closed_loop_parts(system, K)])


def _closed_loop_parts(system: object, K: np.ndarray) -> list[np.ndarray]:
    """``A_cl,0 = A₀ + B₀K`` and ``A_cl,i = A_i + B_i K``: ``A_cl(θ) = A_cl,0 + Σ θ_i A_cl,i``
    ((4.6) is affine in θ)."""
    A0, B0 = (np.asarray(M, dtype=float) for M in (system.A0, system.B0))
    return [A0 + B0 @ K] + [np.asarray(Ai, dtype=float) + np.asarray(Bi, dtype=float) @ K
                            for Ai, Bi in zip(system.A_list, system.B_list, strict=True)]


def _s_l1(system: object, X0: Polytope, K: np.ndarray) -> np.ndarray | None:
    """For a ``𝕏₀`` whose support is ``‖aᵀM‖₁`` (a parallelotope ``{|Tx| <= d}``,
    ``M = T⁻¹ diag(d)``, its ``support_l1_map``): ``L[i] = H_X A_cl,i M`` stacked
    ``(q + 1, n_X, n)``, so that ``s_jr = ‖(L[0] + Σ_i θ^j_i L[i])_r‖₁`` (SPEC §2.20) for all
    vertices of a new ``Θ_k`` is one tensor product (:func:`_s_from_l1`) instead of
    ``n_X · n_θ`` support calls. ``None`` for any other ``𝕏₀``."""
    l1_map = getattr(X0, "support_l1_map", None)
    if not callable(l1_map):
        return None
    M = np.asarray(l1_map(), dtype=float)
    if M.shape != (X0.dim, X0.dim):
        return None
    HX = unit_polytope(X0, "rapsf")
    return np.stack([HX @ P @ M for P in _closed_loop_parts(system, K)])


def _s_from_l1(L: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """``s[r, j]`` for the vertices ``θ^j`` (rows) from :func:`_s_l1`'s ``L``."""
    weights = np.column_stack([np.ones(len(vertices)), vertices])       # (n_θ, q + 1)
    return np.abs(np.tensordot(weights, L, axes=1)).sum(axis=2).T


def _s_from_lps(X0: Polytope, system: object, K: np.ndarray, vertices: np.ndarray,
                supports: LearnedSupports | None = None) -> np.ndarray:
    """``s[r, j] = max_{x∈𝕏₀} [H_X]_r A_cl(θ^j) x`` (SPEC §2.20) for a polytope ``𝕏₀``
    without enumerated vertices: the ``n_X · n_θ`` supports over the one set ``𝕏₀`` from
    the vertices ``supports`` remembers where they verify, the rest as LPs in one solver
    run (:class:`~balustrade.control.rapsf_supports.LearnedSupports`; without it all as
    LPs, :func:`~balustrade.backends.lp.verified_supports`), each verified as
    :meth:`Polytope.support` verifies its LP (session 15: at 5 masses the 480 separate
    ``support`` calls per new ``Θ_k`` were most of a step, ~0.64 s CPU).
    :func:`~balustrade.problems.rapsf.s_constants` (row by row) when an LP does not end
    optimal."""
    HX = unit_polytope(X0, "rapsf")
    D = np.vstack([HX @ Acl for Acl in closed_loop_matrices(system, K, vertices)])
    values = (supports(D) if supports is not None
              else verified_supports(D, X0.H, X0.h, X0.verified_box()))
    if values is None:
        return s_constants(X0, system, K, vertices)
    return values.reshape(len(vertices), HX.shape[0]).T


def _s_from_affine(T: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """``s[r, j]`` for the vertices ``θ^j`` (rows) from :func:`_s_affine`'s ``T``."""
    weights = np.column_stack([np.ones(len(vertices)), vertices])       # (n_θ, q + 1)
    return np.tensordot(weights, T, axes=1).max(axis=2).T


__all__ = ["RAPSF"]
