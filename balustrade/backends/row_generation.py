"""Row generation (a cutting-plane method) for an LP/QP whose inequality rows come in groups.

The problem is the direct backend's lowering (:class:`~balustrade.backends.passes.to_conic.
ConicProgram` without cones): ``min ½yᵀPy + qᵀy`` s.t. ``A_eq y = b_eq``, ``G y <= h``. The
rows of ``G`` carry a group label (``-1``: not grouped, always kept). In (4.5) of the RAPSF
(thesis Chapter 4, SPEC §2.20) a group is one tube row (4.5c) — stage ``i``, facet ``r`` of
𝕏₀ — written once per vertex of ``Θ_k``; at the optimum only a few of a group's rows are
active, so most of the 28644 inequality rows of the 8-mass QP never bind.

:meth:`RowGeneration.run` solves a sequence of reduced QPs with the equality rows, every
ungrouped row and a working set of grouped rows. After each round all rows are evaluated at
the reduced optimum ``y*`` by one sparse product; for each group with a row violated by more
than the tolerance only its ``k`` most violated rows are added (never every violated row: that
was measured in session 11 to end with almost all rows). Rows stay once added; the next solve
starts from this solve's working set (or its rows near active), also shifted by one stage.

**Exactness.** Each reduced QP has a subset of the full QP's constraints, so it is a
relaxation: its optimal value ``f*_red <= f*``. At termination ``y*`` (optimal for the reduced
QP) satisfies every row of the full QP within the tolerance, so it is feasible for it and
``f(y*) >= f*``; with ``f(y*) = f*_red <= f*`` it is optimal for the full QP. The reduced
multipliers, extended by zeros for the rows left out, satisfy the full QP's KKT conditions
(stationarity involves only the rows kept; left-out rows have zero multipliers and are
satisfied, so complementarity holds). The minimizer in the variables the cost is strictly
convex in (the RAPSF's ``v_0``) is therefore the full QP's. **Infeasible** is exact too: if a
relaxation is infeasible the full QP is; its Farkas certificate, extended by zeros, is a
certificate for the full data (the caller checks it on the full data). Any other stop of a
reduced solve (iteration limit, failure) or too many rounds is reported as not solved, and the
caller solves the full QP instead.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from balustrade.backends.direct_engines import (
    _PIQP_STATUS,
    DEFAULT_OPTIONS,
    RawResult,
    _row_blocks,
    _set_options,
)
from balustrade.backends.passes.to_conic import ConicProgram
from balustrade.backends.solution import Status
from balustrade.errors import BalustradeError

#: rounds after which row generation gives up (the caller then solves the full QP)
MAX_ROUNDS = 40
#: what seeds the next solve's working set: the rows near active at this solve ("active")
#: or this solve's whole final working set ("working"), in both cases also shifted by a stage
SEEDS = ("active", "working")
#: a grouped row within this (relative) gap of active at a solve seeds the next solve
ACTIVE_GAP = 1e-6
#: the keys of the direct backend's option ``row_generation`` (keywords of
#: :class:`RowGeneration`; the groups, the stride and the full solve's options come from the
#: OCP and the target)
ROWGEN_KEYS = ("per_round", "seed", "max_rounds", "drop_after", "reduced_options",
               "reuse_solver")


def _positive_int(value: object, name: str, none_ok: bool = False) -> None:
    """Refuse anything but a positive ``int`` (``bool`` included) for ``name``."""
    if none_ok and value is None:
        return
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
        raise BalustradeError(f"row generation: {name} must be a positive integer"
                              f"{' or None' if none_ok else ''}, got {value!r}")


@dataclass
class RowGenStats:
    """What the last :meth:`RowGeneration.run` did."""

    rounds: int = 0
    rows: int = 0          # inequality rows of the last reduced QP
    iterations: int = 0    # interior-point iterations over all rounds
    history: list[int] = field(default_factory=list)  # rows per round
    reused: int = 0        # rounds solved by updating the last PIQP solver (same rows)


def check_setting(per_round: object = 3, seed: object = "working",
                  max_rounds: object = MAX_ROUNDS, drop_after: object = None,
                  reduced_options: object = None, reuse_solver: object = True) -> None:
    """Refuse a bad value of a :data:`ROWGEN_KEYS` keyword (a :class:`BalustradeError`
    naming it); the direct backend calls it for its option ``row_generation`` whether or not
    the OCP has row groups."""
    _positive_int(per_round, "per_round")
    _positive_int(max_rounds, "max_rounds")
    _positive_int(drop_after, "drop_after", none_ok=True)
    if not isinstance(seed, str) or seed not in SEEDS:
        raise BalustradeError(f"row generation: seed must be one of {SEEDS}, got {seed!r}")
    if reduced_options is not None and not isinstance(reduced_options, Mapping):
        raise BalustradeError(f"row generation: reduced_options must be a dict of PIQP "
                              f"settings or None, got {type(reduced_options).__name__}")
    if not isinstance(reuse_solver, bool):
        raise BalustradeError(f"row generation: reuse_solver must be True or False, got "
                              f"{reuse_solver!r}")


class RowGeneration:
    """Row generation on ``prog`` (an LP/QP) with inequality-row groups ``groups`` (one label
    per inequality row of ``prog.A``, i.e. per row after the equality rows; ``-1`` for rows
    always kept). ``per_round``: rows added per violated group and round. ``stride``: the
    number of groups per stage, so that group ``g`` of the next solve is seeded with the
    seed rows of group ``g + stride`` of this one (the receding horizon's shift, at the same
    positions within the group), besides those of group ``g`` itself; ``0``: no shift.
    ``seed`` (:data:`SEEDS`): which rows of this solve seed the next. ``drop_after``: leave
    out of the seed the rows not near active at that many consecutive solves (``None``:
    keep them). ``options``: PIQP settings. ``reduced_options``: settings of the reduced
    solves only (e.g. the KKT solver). ``reuse_solver``: a round whose rows are those of the
    last reduced solve (the same sparsity pattern) updates that PIQP solver's data
    (``update``) instead of setting up a new one; the solve itself is as cold as before
    (PIQP takes no starting point), only the set-up (ordering, symbolic analysis) is saved.
    The defaults (3 rows per group and round, the whole working set as seed, reuse) were the
    fastest on the 8-mass (4.5) in sessions 12 and 13; the preset ``fast-convex-rowgen`` sets
    1 row per group and round, 8–10 % less CPU per 8-mass step (docs/adaptive.md, session
    15)."""

    def __init__(self, prog: ConicProgram, groups: np.ndarray, per_round: int = 3,
                 stride: int = 0, options: dict | None = None,
                 max_rounds: int = MAX_ROUNDS, seed: str = "working",
                 drop_after: int | None = None, reduced_options: dict | None = None,
                 reuse_solver: bool = True):
        if prog.conic:
            raise BalustradeError("row generation: an LP/QP is needed (this problem has "
                                  "second-order cones)")
        self.m0 = sum(m for kind, m in prog.cones if kind == "zero")
        m_in = prog.A.shape[0] - self.m0
        groups = np.asarray(groups, dtype=np.int64).reshape(-1)
        if groups.shape != (m_in,):
            raise BalustradeError(f"row generation: groups must have one label per "
                                  f"inequality row, shape ({m_in},), got {groups.shape}")
        check_setting(per_round=per_round, seed=seed, max_rounds=max_rounds,
                      drop_after=drop_after, reduced_options=reduced_options,
                      reuse_solver=reuse_solver)
        if isinstance(stride, bool) or not isinstance(stride, int | np.integer) or stride < 0:
            raise BalustradeError(f"row generation: stride must be an integer >= 0, got "
                                  f"{stride!r}")
        self.prog, self.groups = prog, groups
        self.per_round, self.stride = int(per_round), int(stride)
        self.max_rounds = int(max_rounds)
        self.seed = seed
        self.drop_after = None if drop_after is None else int(drop_after)
        self._idle = np.zeros(groups.size, dtype=np.int64)  # solves a row was not near active
        self.options = {**DEFAULT_OPTIONS["piqp"], **(options or {})}
        #: PIQP settings of the reduced solves (the full solve's, updated by reduced_options;
        #: a KKT solver may be given by its name)
        self.reduced = {**self.options, **(reduced_options or {})}
        self.always = groups < 0
        self.n_groups = int(groups.max()) + 1 if groups.size else 0
        # the grouped rows sorted by group, and where each group starts in that order
        grouped = np.flatnonzero(~self.always)
        self._order = grouped[np.argsort(groups[grouped], kind="stable")]
        self._P = sp.triu(prog.P).tocsc()
        self._layout: tuple | None = None   # the patterns of A's two blocks (_load)
        self._A_full: sp.csc_matrix | None = None   # A with the values of the last _load
        self._A_eq: sp.csc_matrix | None = None     # its equality block
        self._seed: np.ndarray | None = None   # inequality rows active at the last solve
        self.reuse_solver = reuse_solver
        # the last reduced QP: its rows, G[rows] (CSC) and where its values sit in A.data
        self._red: tuple[np.ndarray, sp.csc_matrix, np.ndarray] | None = None
        self._solver: object | None = None   # the PIQP solver set up for self._red's rows
        self._code: sp.csr_matrix | None = None   # G's pattern, positions in A.data (_load)
        self.stats = RowGenStats()

    # -- data ---------------------------------------------------------------------------------
    def _load(self, A: np.ndarray | None) -> sp.csc_matrix:
        """Take the values ``A`` of the program's ``A`` (``None``: its own): into the full
        matrix (:attr:`_A_full`, CSC on the program's pattern, whose product with ``y`` gives
        every row at once) and into the equality block, which is returned (CSC). The
        patterns, where each block's values sit in ``A.data`` and the matrices themselves
        are built once; later calls overwrite their values in place (no scipy constructor
        with its index checks, and no CSR copy of the 8-mass ``A``'s 3.2e5 values, per
        solve; explicit zeros stay, so no pattern ever changes)."""
        prog = self.prog
        values = prog.A.data if A is None else A
        if self._layout is None:
            # the two blocks as the PIQP engine finds them (CSC, positions in A.data); the
            # inequality block once more in CSR, its positions carried as values 1 … nnz
            # (a value 0 would be a structural zero to scipy)
            eq, ineq = _row_blocks(prog.A, self.m0)
            code = sp.csc_matrix((ineq[2] + 1.0, ineq[0], ineq[1]), shape=ineq[3]).tocsr()
            code.sort_indices()
            at_in = code.data.astype(np.int64) - 1
            self._layout = (eq, (code.indices, code.indptr, at_in, code.shape))
            # G's pattern in CSR with the positions of its values in A.data (+1) as values
            self._code = code  # its values are those positions + 1 already
            i_eq, p_eq, at_eq, s_eq = eq
            self._A_full = sp.csc_matrix((np.array(values, dtype=float), prog.A.indices,
                                          prog.A.indptr), shape=prog.A.shape)
            self._A_eq = sp.csc_matrix((values[at_eq], i_eq, p_eq), shape=s_eq)
            return self._A_eq
        self._A_full.data[:] = values
        self._A_eq.data[:] = values[self._layout[0][2]]
        return self._A_eq

    def _rows_at(self, y: np.ndarray) -> np.ndarray:
        """``G y``: every inequality row of the full QP at ``y`` (one sparse product with
        the values of the last :meth:`_load`)."""
        return (self._A_full @ y)[self.m0:]

    def _split(self, A: np.ndarray | None) -> tuple[sp.csc_matrix, sp.csr_matrix]:
        """The equality block (CSC, :meth:`_load`'s matrix) and the inequality block ``G``
        (a new CSR matrix) of ``A`` with values ``A`` (``None``: the program's own), e.g. to
        inspect a reduced QP; :meth:`run` does not build ``G``."""
        A_eq = self._load(A)
        i_in, p_in, at_in, s_in = self._layout[1]
        return A_eq, sp.csr_matrix((self._A_full.data[at_in], i_in, p_in), shape=s_in)

    def _reduced(self, rows: np.ndarray) -> sp.csc_matrix:
        """``G[rows]`` in CSC with the values of the last :meth:`_load`. For the rows of the
        last call the same matrix is returned with its values overwritten (the same pattern,
        explicit zeros kept: what PIQP's ``update`` needs); for new rows its pattern and
        where its values sit in ``A.data`` are found once."""
        if self._red is not None and np.array_equal(self._red[0], rows):
            _, red, at = self._red
            red.data[:] = self._A_full.data[at]
            return red
        sub = self._code[rows].tocsc()
        at = sub.data.astype(np.int64) - 1
        red = sp.csc_matrix((self._A_full.data[at], sub.indices, sub.indptr), shape=sub.shape)
        self._red, self._solver = (rows.copy(), red, at), None
        return red

    def _tolerance(self, h: np.ndarray, Gy: np.ndarray) -> np.ndarray:
        """The violation above which a row counts as violated: PIQP's own feasibility test
        per row (``eps_abs + eps_rel · max(|Gy|, |h|)``) with the tolerances the reduced
        solves run with (:attr:`reduced`: their feasibility is all the check can rely on)."""
        return self.reduced["eps_abs"] + self.reduced["eps_rel"] * np.maximum(np.abs(Gy),
                                                                              np.abs(h))

    def _initial(self, h: np.ndarray) -> np.ndarray:
        """The first working set: ungrouped rows, the seed of the last solve (shifted by
        :attr:`stride` groups too) or, cold, each group's row most violated at ``y = 0``
        (the smallest ``h``)."""
        work = self.always.copy()
        if self._seed is not None:
            work[self._seed] = True
            if self.stride:
                work |= self._shifted(self._seed)
            return work
        work[self._most_violated(-h, np.ones(h.size, dtype=bool), 1)] = True
        return work

    def _shifted(self, rows: np.ndarray) -> np.ndarray:
        """Rows at the same position within group ``g − stride`` as ``rows`` within ``g``."""
        out = np.zeros(self.groups.size, dtype=bool)
        g = self.groups[rows]
        ok = g >= self.stride
        target = g[ok] - self.stride
        pos = self._pos[rows[ok]]
        start, size = self._start[target], self._size[target]
        fits = pos < size
        out[self._order[start[fits] + pos[fits]]] = True
        return out

    @property
    def _pos(self) -> np.ndarray:
        """Position of each grouped row within its group (in the sorted order)."""
        if not hasattr(self, "_pos_cache"):
            pos = np.full(self.groups.size, -1, dtype=np.int64)
            g = self.groups[self._order]
            starts = np.searchsorted(g, np.arange(self.n_groups))
            sizes = np.searchsorted(g, np.arange(self.n_groups), side="right") - starts
            pos[self._order] = np.arange(self._order.size) - starts[g]
            self._pos_cache, self._start, self._size = pos, starts, sizes
        return self._pos_cache

    def _most_violated(self, viol: np.ndarray, candidate: np.ndarray, k: int) -> np.ndarray:
        """Per group, the (up to) ``k`` candidate rows with the largest ``viol``."""
        rows = self._order[candidate[self._order]]
        if rows.size == 0:
            return rows
        g = self.groups[rows]
        order = np.lexsort((-viol[rows], g))
        rows, g = rows[order], g[order]
        first = np.r_[True, g[1:] != g[:-1]]
        rank = np.arange(rows.size) - np.maximum.accumulate(np.where(first,
                                                                     np.arange(rows.size), 0))
        return rows[rank < k]

    # -- solve ----------------------------------------------------------------------------------
    def _solve_reduced(self, q, A_eq, b_eq, G, h, solver: object | None = None
                       ) -> tuple[RawResult, object]:
        """One reduced QP ``(q, A_eq, b_eq, G, h)`` by PIQP: ``solver`` (set up for a QP of
        the same sparsity pattern) gets the new data by ``update``, else a new solver is set
        up. Returns the result and the solver."""
        import piqp

        has_eq, has_in = A_eq.shape[0] > 0, G.shape[0] > 0
        if solver is not None:
            solver.update(c=q, A=A_eq if has_eq else None, b=b_eq if has_eq else None,
                          G=G if has_in else None, h_u=h if has_in else None)
        else:
            solver = piqp.SparseSolver()
            solver.settings.verbose = False
            options = dict(self.reduced)
            if isinstance(options.get("kkt_solver"), str):
                name = options["kkt_solver"]
                if name not in piqp.KKTSolver.__members__:
                    raise BalustradeError(f"row generation: PIQP has no KKT solver {name!r}; "
                                          f"use one of {', '.join(piqp.KKTSolver.__members__)}")
                options["kkt_solver"] = piqp.KKTSolver.__members__[name]
            _set_options(solver.settings, options, "PIQP")
            solver.setup(self._P, q, A_eq if has_eq else None, b_eq if has_eq else None,
                         sp.csc_matrix(G) if has_in else None, None,
                         h if has_in else None)
        words = str(solver.solve().name)
        # the result's arrays are views of the solver's memory, which a kept solver
        # overwrites at its next solve: copied (np.array; the subtraction and the
        # concatenation below copy too)
        res = solver.result
        z_in = (np.asarray(res.z_u, dtype=float) - np.asarray(res.z_l, dtype=float)) \
            if has_in else np.zeros(0)
        z_eq = np.asarray(res.y, dtype=float) if has_eq else np.zeros(0)
        return RawResult(_PIQP_STATUS.get(words, Status.FAILED), f"PIQP: {words}",
                         np.array(res.x, dtype=float), np.concatenate([z_eq, z_in]),
                         int(res.info.iter)), solver

    def _round(self, q, A_eq, b_eq, h, rows: np.ndarray) -> RawResult:
        """The reduced QP of the rows ``rows``: by the last solver updated when it was set up
        for these rows (:attr:`reuse_solver`), else by a new one. A reused solver's answer
        other than optimal/infeasible is not taken: the round is solved again by a new
        solver (as without reuse), so reuse never changes what a round reports."""
        done = (Status.OPTIMAL, Status.INFEASIBLE)
        red = self._reduced(rows)          # forgets the solver when the rows changed
        reuse = self._solver if self.reuse_solver else None
        raw, solver = self._solve_reduced(q, A_eq, b_eq, red, h[rows], reuse)
        if reuse is not None and raw.status in done:
            self.stats.reused += 1
        elif reuse is not None:
            first = raw.iterations
            raw, solver = self._solve_reduced(q, A_eq, b_eq, red, h[rows])
            raw.iterations += first
        # a solver that stopped otherwise is not kept (the next round sets up anew)
        self._solver = solver if raw.status in done else None
        return raw

    def run(self, q: np.ndarray, b: np.ndarray, A: np.ndarray | None = None,
            cold: bool = False) -> RawResult:
        """Solve the full QP ``(q, b, A)`` by row generation. ``OPTIMAL`` and ``INFEASIBLE``
        results carry multipliers for every row of the full QP (zero for rows never added);
        anything else is ``FAILED``/``MAX_ITERATIONS`` with the reason: the caller solves the
        full QP then. ``cold``: ignore the rows of the last solve."""
        A_eq = self._load(A)
        b_eq, h = b[:self.m0], b[self.m0:]
        if cold:
            self._seed = None
        work = self._initial(h)
        stats = RowGenStats()
        self.stats = stats
        while True:
            rows = np.flatnonzero(work)
            stats.rounds += 1
            stats.rows = rows.size
            stats.history.append(rows.size)
            raw = self._round(q, A_eq, b_eq, h, rows)
            stats.iterations += raw.iterations
            if raw.status == Status.INFEASIBLE:
                raw.z = self._full_z(raw.z, rows)
                raw.words += f" (a relaxation with {rows.size} of {h.size} rows, round " \
                             f"{stats.rounds}: the full QP is infeasible too)"
                raw.iterations = stats.iterations
                self._seed = None
                return raw
            if raw.status != Status.OPTIMAL:
                self._seed = None
                return RawResult(Status.FAILED, f"row generation: round {stats.rounds} "
                                 f"({rows.size} rows) stopped with {raw.words}", None, None,
                                 stats.iterations)
            Gy = self._rows_at(raw.y)
            viol = Gy - h
            bad = (viol > self._tolerance(h, Gy)) & ~work
            if not bad.any():
                break
            if stats.rounds >= self.max_rounds:
                self._seed = None
                return RawResult(Status.FAILED, f"row generation: {bad.sum()} rows still "
                                 f"violated after {stats.rounds} rounds", None, None,
                                 stats.iterations)
            work[self._most_violated(viol, bad, self.per_round)] = True
        z = self._full_z(raw.z, rows)
        # the seed of the next solve: grouped rows within ACTIVE_GAP of active, or every
        # grouped row of the last working set
        near = viol >= -ACTIVE_GAP * (1.0 + np.abs(h))
        self._idle = np.where(near, 0, self._idle + 1)
        keep = near if self.seed == "active" else work
        if self.drop_after is not None:              # rows idle for drop_after solves go
            keep = keep & (self._idle < self.drop_after)
        self._seed = np.flatnonzero(keep & ~self.always)
        raw.z, raw.iterations = z, stats.iterations
        raw.words += f" (row generation: {stats.rounds} rounds, {rows.size} of {h.size} " \
                     "inequality rows)"
        return raw

    def _full_z(self, z: np.ndarray | None, rows: np.ndarray) -> np.ndarray | None:
        """Reduced multipliers ``[z_eq, z_rows]`` as multipliers of every row of the full QP
        (zero for the rows left out)."""
        if z is None:
            return None
        full = np.zeros(self.prog.A.shape[0])
        full[:self.m0] = z[:self.m0]
        full[self.m0 + rows] = z[self.m0:]
        return full


__all__ = ["ACTIVE_GAP", "MAX_ROUNDS", "ROWGEN_KEYS", "SEEDS", "RowGenStats", "RowGeneration",
           "check_setting"]
