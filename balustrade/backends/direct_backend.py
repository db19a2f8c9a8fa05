"""The direct conic backend: a convex OCP lowered once to the solvers' own parametric
interfaces (issue #14 §1).

The chain :data:`balustrade.backends.passes.DIRECT_CHAIN` classifies the OCP
(:mod:`~balustrade.backends.passes.classify`, refusing a nonconvex block by name) and builds
the conic data ``P, A, K`` once (:mod:`~balustrade.backends.passes.to_conic`); a solve only
computes ``q = q0 + Q p`` and ``b = b0 + B p + D φ(p)`` (and, for rows with coefficients
affine in the parameters, the values ``A.data + A_param p`` of ``A(p)`` on its fixed
pattern) and hands them to a solver set up at compile time
(:mod:`~balustrade.backends.direct_engines`): PIQP for LPs/QPs, Clarabel when a cone is
needed. No cvxpy canonicalization is run per solve. Every re-solve (the feasibility check,
the unequilibrated and the rescaled retries, the solve with the large rows) gets the same
``A(p)``.

Statuses follow :mod:`~balustrade.backends.cvxpy_backend`, with a stricter "infeasible": the
verdict stands only if the solver's certificate passes a numerical Farkas check against the
problem data (:mod:`~balustrade.backends.farkas`) or the constraints alone are found
infeasible by the other engine (PIQP ↔ Clarabel for LPs/QPs; for cones, Clarabel with a
certificate that passes the check); otherwise it becomes ``failed`` with the reason. Rows
with large bounds are imposed by a second solve only when violated; a failed solve of a
problem with weights above :data:`~balustrade.backends.cvxpy_backend.BIG_WEIGHT` is retried
with the cost rescaled (then at best ``optimal_inaccurate``). Multipliers per block have the
sign convention of the other backends (``≥ 0`` for ``g <= 0`` rows, ``∇f + Σ λ ∇g = 0``).
"""

from __future__ import annotations

import numbers
import time
from collections.abc import Callable, Iterator, Mapping

import numpy as np
import scipy.sparse as sp

from balustrade.backends.casadi_fast import Buffered
from balustrade.backends.cvxpy_backend import BIG_WEIGHT, LARGE_BOUND
from balustrade.backends.direct_engines import DIRECT_SOLVERS, RawResult, RowMiss, make_engine
from balustrade.backends.farkas import check_farkas
from balustrade.backends.passes import DIRECT_CHAIN, run_chain
from balustrade.backends.passes.classify import Classify
from balustrade.backends.passes.to_conic import (
    CONE_HEAD,
    LINEAR,
    ConicProgram,
    ToConic,
)
from balustrade.backends.row_generation import ROWGEN_KEYS, RowGeneration, check_setting
from balustrade.backends.solution import Solution, Status
from balustrade.dsl.ocp import OCP
from balustrade.errors import BalustradeError, SolverError

#: statuses after which a solve is retried (unequilibrated, then with the cost rescaled)
_RETRY = (Status.FAILED, Status.MAX_ITERATIONS, Status.OPTIMAL_INACCURATE)


#: the option of a target without a solver that picks the engine of an LP/QP by its size
#: (preset ``"fast-convex-sized"``): DAQP (:mod:`~balustrade.backends.daqp_engine`) when the
#: lowered program's dense constraint matrix has at most this many entries, else PIQP
DENSE_CHOICE = "daqp_max_entries"


def _by_size(program: ConicProgram, limit: object, name: str) -> str:
    """The engine of the LP/QP ``program`` when the target names no solver: ``"daqp"`` when
    ``limit`` (option :data:`DENSE_CHOICE`) is given and ``m · n`` of the lowered program
    (every row, the large ones included) is at most ``limit``, else ``"piqp"``."""
    if limit is None:
        return "piqp"
    if isinstance(limit, bool) or not isinstance(limit, numbers.Integral) or limit < 1:
        raise SolverError(f"{name}: option {DENSE_CHOICE} must be a positive int, got "
                          f"{limit!r}")
    m, n = program.A.shape
    if program.large is not None:   # set aside, but solved with when a bound binds
        m += program.large.A.shape[0]
    return "daqp" if m * n <= limit else "piqp"


def _run(engine: object, q: np.ndarray, b: np.ndarray, A: np.ndarray | None) -> RawResult:
    """``engine.run`` with the values of ``A(p)`` only when ``A`` depends on ``p``."""
    return engine.run(q, b) if A is None else engine.run(q, b, A)


class BlockDuals(Mapping):
    """The multipliers per constraint block of one solve (:attr:`Solution.dual`), computed
    on first read: no closed loop of the library reads them per step, and converting the
    solver's cone duals and splitting them into blocks took ~0.5 ms per solve at N = 200
    (two solves per step of Algorithm 5.2). Reads, copies and pickles as the ``dict`` it
    stands for (a copy or a pickle is that plain ``dict``); until it is read it holds the
    solver's duals (as the solver returned them), afterwards only the blocks."""

    def __init__(self, compute: Callable[[ConicProgram, np.ndarray | None],
                                         dict[str, np.ndarray]],
                 prog: ConicProgram, raw: RawResult):
        self._source: tuple | None = (compute, prog, raw)
        self._blocks: dict[str, np.ndarray] | None = None

    def _values(self) -> dict[str, np.ndarray]:
        if self._blocks is None:
            compute, prog, raw = self._source
            self._blocks, self._source = compute(prog, raw.z), None
        return self._blocks

    def __getitem__(self, key: str) -> np.ndarray:
        return self._values()[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self._values())

    def __len__(self) -> int:
        return len(self._values())

    def __repr__(self) -> str:
        return repr(self._values())

    def __reduce__(self) -> tuple:
        return dict, (dict(self._values()),)


class DirectCompiled:
    """A convex OCP compiled to Clarabel/PIQP: call :meth:`solve` with parameter values."""

    backend = "direct"

    def __init__(self, ocp: OCP, solver: str | None = None, options: dict | None = None):
        self.ocp = ocp
        program, _ = run_chain(DIRECT_CHAIN, ocp)
        self.program: ConicProgram = program
        self.conic = program.conic
        if solver is not None and (not isinstance(solver, str)
                                   or solver.lower() not in DIRECT_SOLVERS):
            raise SolverError(f"{ocp.name}: the direct backend has no solver {solver!r}; use "
                              f"one of {', '.join(DIRECT_SOLVERS)} (or None: PIQP for LPs/QPs, "
                              "Clarabel for cones)")
        if options is not None and not isinstance(options, Mapping):
            raise SolverError(f"{ocp.name}: options must be a dict of solver options or None, "
                              f"got {type(options).__name__}")
        self.options = dict(options or {})
        small = self.options.pop(DENSE_CHOICE, None)
        if small is not None and solver is not None:
            raise SolverError(f"{ocp.name}: option {DENSE_CHOICE} chooses the solver by size; "
                              f"it takes a target without one, not solver {solver!r}")
        self.solver_name = solver.lower() if solver else (
            "clarabel" if self.conic else _by_size(program, small, ocp.name))
        rowgen = self.options.pop("row_generation", None)
        self.engine = make_engine(self.solver_name, program, self.options)
        #: row generation over the OCP's grouped rows (option ``row_generation``), or None
        self.rowgen = self._row_generation(rowgen) if rowgen is not None else None
        self._row_check: RowMiss | None = None  # row generation's answers checked
        self.cost_scale = program.cost_scale
        self._full: tuple[ConicProgram, object] | None = None  # with the large rows
        self._feasibility: dict = {}  # per program: the engine checking "infeasible"
        self._objective: dict = {}  # per program: its cost through preallocated buffers
        self._scaled = None  # built on the first failure with big weights
        # Clarabel without equilibration, built on the first inexact solve (False: none)
        self._second = None if self.solver_name == "clarabel" and \
            "equilibrate_enable" not in self.options else False

    def _rowgen_rows(self, A: np.ndarray | None) -> RowMiss:
        """The row check of the engines (:class:`~balustrade.backends.direct_engines.RowMiss`)
        for row generation's answers, which come from reduced solves the engines never see
        (review R1, session 15): an ``optimal`` missing a full row by more than ``ROW_TOL`` in
        the row's own unit goes to the full QP."""
        if self._row_check is None:
            self._row_check = RowMiss(self.program)
        if A is not None:
            self._row_check.update(A)
        return self._row_check

    # -- solve -------------------------------------------------------------------------
    def solve(self, params: dict[str, object] | None = None,
              warm_start: Solution | dict[str, object] | None = None) -> Solution:
        """Solve with the given parameter values. ``warm_start`` is accepted for the common
        interface and ignored: neither interior-point solver takes a starting point through
        its Python interface, so every solve is cold and depends on ``params`` only (the
        opt-in solver ``"daqp"`` starts from its own last working set instead, its answers
        KKT-checked: :mod:`~balustrade.backends.daqp_engine`). With
        the option ``row_generation`` (:mod:`~balustrade.backends.row_generation`) the
        reduced QPs start from the previous solve's rows; the answer is the full QP's (exact
        at termination, to the solver's tolerance); a reduced solve that is not optimal or
        infeasible, or an "infeasible" that :meth:`_check_infeasible` does not establish on
        the full data, is replaced by the full solve."""
        p = self.ocp.pack_parameters(params)
        prog = self.program
        start = time.perf_counter()
        q, b, A = prog.q(p), prog.b(p), prog.A_data(p)
        if self.rowgen is not None:
            raw = self.rowgen.run(q, b, A)
            if raw.status == Status.OPTIMAL:  # the engines' row check, on the full rows
                raw.status, raw.words = self._rowgen_rows(A).verdict(
                    raw.status, raw.words, raw.y[:prog.A.shape[1]], b)
            if raw.status not in (Status.OPTIMAL, Status.INFEASIBLE):  # solve it whole
                first = raw.words
                raw = _run(self.engine, q, b, A)
                raw.words = f"{raw.words} (the full QP; {first})"
        else:
            raw = _run(self.engine, q, b, A)
        message = raw.words
        if raw.status == Status.INFEASIBLE:
            raw, message = self._check_infeasible(raw, prog, b, A)
            if self.rowgen is not None and raw.status == Status.FAILED:
                # a relaxation's "infeasible" that the checks do not establish (e.g. the
                # full constraints are feasible): the full QP decides
                raw = _run(self.engine, q, b, A)
                raw.words = f"{raw.words} (the full QP; row generation: {message})"
                message = raw.words
                if raw.status == Status.INFEASIBLE:
                    raw, message = self._check_infeasible(raw, prog, b, A)
        if prog.large is not None and raw.status != Status.INFEASIBLE \
                and not self._within_large(raw, p):
            first = "violated them" if raw.status.success else raw.status
            full, engine = self._full_problem()
            prog = full
            b_full, A_full = full.b(p), full.A_data(p)
            raw = _run(engine, full.q(p), b_full, A_full)
            words = raw.words
            if raw.status == Status.INFEASIBLE:
                raw, words = self._check_infeasible(raw, full, b_full, A_full)
            message = (f"{words} (with the {self.program.large.c.size} large bounds/rows "
                       f"|b| >= {LARGE_BOUND:g}; the solve without them: {first})")
        if raw.status in _RETRY and prog is self.program and self._second is not False:
            raw, message = self._unequilibrated(raw, message, q, b, A)
        if raw.status in _RETRY and self.cost_scale > BIG_WEIGHT and prog is self.program:
            raw, message = self._rescaled(raw, message, p)
        elapsed = time.perf_counter() - start
        n = prog.n_w
        usable = raw.status.success and raw.y is not None and np.all(np.isfinite(raw.y))
        w = raw.y[:n].copy() if usable else np.full(n, np.nan)
        objective = self._cost(prog, w, p) if usable else np.nan
        dual = BlockDuals(self._duals, prog, raw) if usable else {}
        return Solution(status=raw.status, objective=objective,
                        primal=self.ocp.unpack_variables(w), dual=dual, solve_time=elapsed,
                        iterations=raw.iterations, backend="direct",
                        solver=raw.solver or self.solver_name, p=p, message=message)

    def _row_generation(self, setting: object) -> RowGeneration | None:
        """:class:`~balustrade.backends.row_generation.RowGeneration` for the option
        ``row_generation`` (``True`` or a dict of :class:`RowGeneration`'s keywords, e.g.
        ``{"per_round": 2, "seed": "working"}``) when the OCP marks groups of
        inequality rows (``ocp.row_groups``: block name → a group label per row, and
        ``ocp.row_group_stride``, e.g. :func:`balustrade.problems.rapsf.rapsf_problem`) and
        the problem is an LP/QP solved by PIQP; ``None`` (every solve whole) otherwise, and
        for ``False``. The setting and ``ocp.row_groups`` are checked here, before any solve
        (:class:`~balustrade.errors.SolverError` naming the key or the block)."""
        where = f"{self.ocp.name}: option row_generation"
        if isinstance(setting, bool):
            if not setting:
                return None
            setting = {}
        elif isinstance(setting, Mapping):
            setting = dict(setting)
            unknown = sorted(set(map(str, setting)) - set(ROWGEN_KEYS))
            if unknown:
                raise SolverError(f"{where}: unknown key(s) {', '.join(unknown)}; use "
                                  f"{', '.join(ROWGEN_KEYS)} (the stride comes from "
                                  "ocp.row_group_stride, the solver options from the target)")
        else:
            raise SolverError(f"{where} must be True/False or a dict of "
                              f"{', '.join(ROWGEN_KEYS)}, got {type(setting).__name__}")
        try:
            check_setting(**setting)
        except BalustradeError as err:
            raise SolverError(f"{where}: {err}") from None
        groups = getattr(self.ocp, "row_groups", None)
        if not groups or self.solver_name != "piqp" or self.program.conic:
            return None
        prog = self.program
        m0 = sum(m for kind, m in prog.cones if kind == "zero")
        labels = np.full(prog.A.shape[0] - m0, -1, dtype=np.int64)
        blocks = {block.name: block.rows for block in self.ocp.blocks}
        for name, ids in groups.items():
            ids = np.asarray(ids)
            if name not in blocks:
                raise SolverError(f"{self.ocp.name}: ocp.row_groups names {name!r}, which is "
                                  "no constraint block of the OCP")
            if ids.shape != (blocks[name],) or not np.issubdtype(ids.dtype, np.integer):
                raise SolverError(f"{self.ocp.name}: ocp.row_groups[{name!r}] must be one "
                                  f"integer group label per row, shape ({blocks[name]},), got "
                                  f"shape {ids.shape} of {ids.dtype}")
            for dm in prog.duals.get(name, []):
                if dm.mode != LINEAR or np.any(dm.at < m0):
                    return None                    # not plain inequality rows: no groups
                labels[dm.at - m0] = ids[dm.rows]
        return RowGeneration(prog, labels, stride=int(getattr(self.ocp, "row_group_stride", 0)),
                             options=self.options, **setting)

    def confirm_infeasible(self, p: np.ndarray, said_by: str, words: str,
                           full: bool = False) -> tuple[bool, str]:
        """Whether the verdict "infeasible" that another solve of this OCP's constraints at
        the parameters ``p`` gave (the solver ``said_by``, e.g. the cvxpy backend's, with
        the message ``words``, no certificate of its own) is established by independent
        evidence: the checks of :meth:`_check_infeasible` with ``said_by`` in the place of
        this backend's solver (a Farkas certificate of the feasibility solve that passes
        :func:`~balustrade.backends.farkas.check_farkas`, or for an LP/QP the "infeasible"
        of an engine other than ``said_by``). ``full=True`` checks the constraints with the
        large bounds/rows too (a verdict of the full problem, which :attr:`program` leaves
        out). ``(confirmed, message)``."""
        prog = self._full_problem()[0] if full else self.program
        b, A = prog.b(p), prog.A_data(p)
        raw = RawResult(Status.INFEASIBLE, words, None, None, 0)
        raw, message = self._check_infeasible(raw, prog, b, A, said_by)
        return raw.status == Status.INFEASIBLE, message

    def _check_infeasible(self, raw: RawResult, prog: ConicProgram, b: np.ndarray,
                          A: np.ndarray | None, said_by: str | None = None
                          ) -> tuple[RawResult, str]:
        """An "infeasible" verdict stands only on evidence beyond the solver's word (a
        tolerance, a badly scaled weight or a bug can make a solver declare a feasible
        problem infeasible, and re-asking the same solver can repeat the mistake):

        1. the solver's own certificate ``z`` passes the numerical Farkas check
           (:func:`~balustrade.backends.farkas.check_farkas`: ``z ∈ K*``, ``Aᵀz ≈ 0``,
           ``bᵀz < 0`` on the problem data, scaled); else
        2. the constraints alone (no cost) are solved by the *other* engine for LPs/QPs
           (PIQP ↔ Clarabel; Clarabel for cones): a feasible point overturns the verdict, an
           "infeasible" with a certificate that passes the check, or (LP/QP) the other
           engine's independent "infeasible", confirms it.

        ``said_by`` names the solver that gave the verdict (default: the one that answered,
        ``raw.solver`` — e.g. PIQP after the DAQP engine's fallback — else this backend's
        engine); the message starts with it, and step 2 never counts that solver's own
        "infeasible" as a confirmation. Its verdict without a certificate (``raw.z``
        ``None``) rests on step 2 alone. Anything else is ``failed`` with the reason —
        never ``infeasible``."""
        said_by = said_by or raw.solver or self.solver_name
        words = f"said infeasible by {said_by}: {raw.words}"
        A_mat = prog.A if A is None else sp.csc_matrix((A, prog.A.indices, prog.A.indptr),
                                                       shape=prog.A.shape)
        own = check_farkas(A_mat, b, prog.cones, raw.z)
        if own.valid:
            return raw, f"{words}; certificate checked: {own}"
        name, engine = self._checker(prog)
        check = _run(engine, np.zeros(prog.n_y), b, A)
        head = f"{words}, but its certificate does not hold ({own})" if raw.z is not None \
            else f"{words} (no certificate of its own to check)"
        if check.status == Status.INFEASIBLE:
            theirs = check_farkas(A_mat, b, prog.cones, check.z)
            if theirs.valid:
                return raw, (f"{head}; the {name} feasibility solve's certificate does: "
                             f"{theirs}")
            if name != said_by:
                return raw, (f"{head}; confirmed by {name} on the constraints alone "
                             f"({check.words}; its certificate: {theirs})")
        failed = RawResult(Status.FAILED, raw.words, None, None, raw.iterations, raw.solver)
        if check.status.success:
            return failed, (f"{head}, and the constraints alone are feasible ({name} "
                            f"feasibility solve: {check.words}): the verdict is numerical")
        return failed, (f"{head}; not confirmed by the {name} feasibility solve "
                        f"({check.words}): infeasibility not established")

    def _cost(self, prog: ConicProgram, w: np.ndarray, p: np.ndarray) -> float:
        """The OCP's own cost at ``(w, p)`` (:attr:`ConicProgram.objective`), evaluated
        through :class:`~balustrade.backends.casadi_fast.Buffered` (the same CasADi function
        and the same value; a plain call converts ``w`` and ``p`` to ``DM`` first, ~0.2 ms
        at N = 200)."""
        if id(prog) not in self._objective:
            self._objective[id(prog)] = Buffered(prog.objective)
        value = self._objective[id(prog)](w, p)[0]
        return float(value[0]) if value.size else 0.0  # a structurally zero cost: no entry

    def _checker(self, prog: ConicProgram) -> tuple[str, object]:
        """The engine of the feasibility check of ``prog`` (cost 0): the other solver for an
        LP/QP, Clarabel for a conic problem; built once per program."""
        if id(prog) not in self._feasibility:
            if prog.conic:
                name, options = "clarabel", (self.options if self.solver_name == "clarabel"
                                             else {})
            else:
                name = "piqp" if self.solver_name == "clarabel" else "clarabel"
                options = {}
            engine = make_engine(name, prog, options, P=sp.csc_matrix(prog.P.shape),
                                 q=np.zeros(prog.n_y))
            self._feasibility[id(prog)] = (name, engine)
        return self._feasibility[id(prog)]

    def _within_large(self, raw: RawResult, p: np.ndarray) -> bool:
        """The solution exists and satisfies the large rows left out of the problem."""
        if not raw.status.success or raw.y is None:
            return False
        large = self.program.large
        residual = large.A @ raw.y[:self.program.n_w] + large.c
        if large.B.shape[1]:
            residual = residual + large.B @ p
        return bool(np.all(residual <= 1e-12 * np.abs(large.c)))

    def _full_problem(self) -> tuple[ConicProgram, object]:
        if self._full is None:
            classified, _ = Classify().apply(self.ocp)
            full, _ = ToConic(with_large=True).apply(classified)
            self._full = (full, make_engine(self.solver_name, full, self.options))
        return self._full

    def _unequilibrated(self, raw: RawResult, message: str, q: np.ndarray, b: np.ndarray,
                        A: np.ndarray | None) -> tuple[RawResult, str]:
        """Re-solve with Clarabel's equilibration off: on the robust filter (5.16) of the
        rendezvous far from the origin the equilibrated solve stops "AlmostSolved" where the
        unequilibrated one converges to the tolerances. Kept only if it converges."""
        if self._second is None:
            self._second = make_engine(self.solver_name, self.program,
                                       {**self.options, "equilibrate_enable": False})
        retry = _run(self._second, q, b, A)
        if retry.status == Status.OPTIMAL:
            retry.iterations += raw.iterations
            return retry, f"{retry.words} (without equilibration; first: {raw.words})"
        return raw, f"{message}; without equilibration: {retry.words}"

    def _rescaled(self, raw: RawResult, message: str, p: np.ndarray
                  ) -> tuple[RawResult, str]:
        """Re-solve with the cost divided by :attr:`cost_scale` (weights of 1e9 and more make
        the multipliers huge); the minimizer is the same but accurate only relative to the
        largest weight, hence at best ``optimal_inaccurate``."""
        prog, scale = self.program, self.cost_scale
        if self._scaled is None:
            self._scaled = make_engine(self.solver_name, prog, self.options,
                                       P=(prog.P / scale).tocsc(), q=prog.q0 / scale)
        retry = _run(self._scaled, prog.q(p) / scale, prog.b(p), prog.A_data(p))
        if raw.status == Status.OPTIMAL_INACCURATE and retry.status != Status.OPTIMAL:
            return raw, message
        if retry.status.success:
            retry.z = None if retry.z is None else retry.z * scale
            retry.status = Status.OPTIMAL_INACCURATE
            return retry, (f"{message}; solved with the cost scaled by 1/{scale:.3g}: "
                           f"{retry.words}")
        return raw, f"{message}; with the cost scaled by 1/{scale:.3g}: {retry.words}"

    def _duals(self, prog: ConicProgram, z: np.ndarray | None) -> dict[str, np.ndarray]:
        out = {}
        for block in self.ocp.blocks:
            values = np.zeros(block.rows)
            if z is not None:
                for dm in prog.duals.get(block.name, []):
                    if dm.mode == LINEAR:
                        values[dm.rows] = dm.factor * z[dm.at]
                    elif dm.mode == CONE_HEAD:
                        values[dm.rows] = dm.factor * z[dm.at[0]]
                    else:
                        values[dm.rows] = dm.factor * (z[dm.at[0]] + z[dm.at[1]]) / np.sqrt(2.0)
            out[block.name] = values
        return out
