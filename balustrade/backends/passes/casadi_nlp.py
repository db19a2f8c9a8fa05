"""The last pass of the CasADi chain: a :class:`~balustrade.backends.passes.epigraph.
SmoothProblem` becomes the data ``nlpsol`` takes (:class:`NLPData`): the ``{x, p, f, g}``
dictionary and the numeric bounds and initial point, all read from the one layout.

:func:`compact_nlp` gives the same NLP in the compact lowering (issue #14 §3): MX, with each
dynamics block one SX stage function mapped over the horizon, so that generated C holds each
stage derivative once (``backends.casadi_backend.LOWERINGS``; the C emitters' default)."""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from balustrade.backends.passes.base import Pass
from balustrade.backends.passes.epigraph import SmoothProblem
from balustrade.dsl.layout import Layout
from balustrade.dsl.ocp import OCP, Block, BlockTag


@dataclass(frozen=True)
class NLPData:
    """``nlpsol``'s problem (``nlp``) and its numeric data: bounds on ``x`` and ``g`` and
    the default initial point ``x0`` (the user's ``init``, zeros for added blocks)."""

    nlp: dict
    layout: Layout
    lbx: np.ndarray
    ubx: np.ndarray
    lbg: np.ndarray
    ubg: np.ndarray
    x0: np.ndarray
    block_rows: dict[str, slice]
    n_g_user: int


class CasadiNLP(Pass):
    """SmoothProblem → :class:`NLPData` (nothing to invert: the variables are the same)."""

    name = "casadi-nlp"

    def accepts(self, problem: object) -> bool:
        return isinstance(problem, SmoothProblem)

    def apply(self, sp: SmoothProblem) -> tuple[NLPData, None]:
        lbx, ubx = sp.variables.bounds()
        nlp = {"x": sp.w, "p": sp.p, "f": sp.f, "g": sp.g}
        return NLPData(nlp, sp.variables, lbx, ubx, sp.lbg, sp.ubg, sp.variables.initial(),
                       sp.block_rows, sp.n_g_user), None


def as_dm(data: NLPData) -> dict[str, ca.DM]:
    """The bounds as CasADi ``DM`` (converted once, passed to every solve)."""
    return {k: ca.DM(getattr(data, k)) for k in ("lbx", "ubx", "lbg", "ubg")}


# -- the compact lowering (issue #14 §3): one stage function mapped over the horizon -----
@dataclass(frozen=True)
class StageMap:
    """A constraint block made of ``N`` identical stage functions: rows ``rows`` of ``g``
    are ``vec([F(v_0), …, F(v_{N−1})])`` with ``v_i`` = the decision-vector entries
    ``index[:, i]`` and the full parameter vector ``p`` (shared by every stage)."""

    block: str
    rows: slice
    function: ca.Function
    index: np.ndarray  # (n_stage_vars, N) positions in the decision vector


def _instructions(fn: ca.Function) -> list[tuple]:
    """The algorithm of an SX function, instruction by instruction (operation, inputs,
    outputs, constant): equal lists mean the same computation, bit for bit."""
    return [(fn.instruction_id(k), tuple(fn.instruction_input(k)),
             tuple(fn.instruction_output(k)), fn.instruction_constant(k))
            for k in range(fn.n_instructions())]


def _positions(w: ca.SX) -> dict[int, int]:
    """Element hash of each scalar symbol of ``w`` → its position in ``w``."""
    return {w.nz[k].element_hash(): k for k in range(w.numel())}


def dynamics_stage_map(data: NLPData, ocp: OCP, block: Block) -> StageMap | None:
    """The dynamics block ``x_{i+1} − f(x_i, u_i, w, θ) = 0`` (:meth:`OCP.dynamics`) as one
    stage function ``F(x_i, u_i, x_{i+1}, p)`` mapped over ``i ∈ I[0, N−1]``, or ``None``
    when the block is not that (rows not ``nx·N``, a stage that depends on other decision
    variables, or stages that are not the same computation: every stage's SX algorithm is
    compared with stage 0's, instruction by instruction, so the map is exact)."""
    sys, N = ocp.system, ocp.N
    rows = data.block_rows.get(block.name)
    if sys is None or ocp.x is None or ocp.u is None or rows is None \
            or rows.stop - rows.start != sys.nx * N:
        return None
    g, w, p = data.nlp["g"], data.nlp["x"], data.nlp["p"]
    where = _positions(w)
    nx = sys.nx
    stage0, index = None, []
    for i in range(N):
        args = [ocp.x[:, i], ocp.u[:, i], ocp.x[:, i + 1]]
        r = g[rows.start + i * nx: rows.start + (i + 1) * nx]
        try:
            fn = ca.Function("stage", [*args, p], [r], ["x", "u", "x_next", "p"], ["r"])
        except RuntimeError:  # free symbols: the stage reads other decision variables
            return None
        if stage0 is None:
            stage0, algorithm = fn, _instructions(fn)
        elif _instructions(fn) != algorithm:
            return None
        v = ca.vertcat(*args)
        index.append([where[v.nz[k].element_hash()] for k in range(v.numel())])
    return StageMap(block.name, rows, stage0, np.array(index, dtype=np.int64).T)


def compact_nlp(data: NLPData, ocp: OCP) -> CompactNLP:
    """``data.nlp`` in the compact lowering (:class:`CompactNLP`): the same ``{x, p, f,
    g}`` (same variables, rows and values) built in MX, with each dynamics block one SX
    stage function ``Function.map``-ped over the horizon (:func:`dynamics_stage_map`) and
    every other row and the cost one SX function of ``(w, p)``.

    Why (issue #14 §3): in the expanded SX lowering the derivatives of ``g`` are written
    out for every stage (the cart-pole PCBF problem, RK4, N = 20: 2.1 MB of C for the
    pair). Here the Jacobian of a map is a map of the stage's directional derivatives and
    the Hessian of its Lagrangian a map of a forward-over-reverse derivative, so each
    appears once in the generated code; blocks that are not a clean stage map stay in the
    SX function, whose derivatives :meth:`CompactNLP.derivatives` writes out exactly (in
    MX its Jacobian would be one forward sweep per colour of the whole function)."""
    w, p, f, g = (data.nlp[k] for k in ("x", "p", "f", "g"))
    maps = [m for b in ocp.blocks if b.tag == BlockTag.DYNAMICS
            for m in [dynamics_stage_map(data, ocp, b)] if m is not None]
    maps.sort(key=lambda m: m.rows.start)
    W, P = ca.MX.sym("w", w.numel()), ca.MX.sym("p", p.numel())
    cuts = [0, *[k for m in maps for k in (m.rows.start, m.rows.stop)], g.numel()]
    rest = [g[cuts[2 * j]: cuts[2 * j + 1]] for j in range(len(maps) + 1)]
    mapped = [MappedStages(m, W, P) for m in maps]
    return CompactNLP(w, p, f, ca.vertcat(*rest), [r.numel() for r in rest], W, P, mapped)


def _scatter(stage: ca.Sparsity, index: np.ndarray, shape: tuple[int, int], row_index:
             np.ndarray | None) -> tuple[ca.Sparsity, ca.DM]:
    """Where the nonzeros of ``N`` stage blocks (sparsity ``stage``, the blocks side by side
    as a map returns them) go in a ``shape`` matrix: block ``i``'s entry ``(a, b)`` goes to
    row ``row_index[a, i]`` (``i·rows + a`` when ``None``) and column ``index[b, i]``.
    Returns the matrix's sparsity and the constant 0/1 matrix ``S`` with ``nz = S ·
    nz_blocks`` (entries that land on the same place are summed: a Hessian's overlap)."""
    rows_s, cols_s = stage.get_triplet()
    n = index.shape[1]
    rows, cols = [], []
    for i in range(n):
        for a, b in zip(rows_s, cols_s):
            rows.append(int(row_index[a, i]) if row_index is not None
                        else i * stage.size1() + a)
            cols.append(int(index[b, i]))
    sp, mapping = ca.Sparsity.triplet(shape[0], shape[1], rows, cols, True)
    # mapping[k]: the nonzero of sp that triplet k lands on
    ones = [1.0] * len(mapping)
    S = ca.DM(ca.Sparsity.triplet(sp.nnz(), len(mapping), list(mapping),
                                  list(range(len(mapping)))), ones)
    return sp, S


class MappedStages:
    """A :class:`StageMap` in the MX NLP: the rows ``vec([F(v_0), …])`` of the stage
    function mapped over the horizon, and their first and second derivatives from the
    stage's own SX Jacobian and Hessian (exact sparse expressions, written once and
    mapped), scattered into the NLP's matrices by constant sparse maps."""

    def __init__(self, m: StageMap, W: ca.MX, P: ca.MX):
        self.stage, self.W, self.P = m, W, P
        fn, n = m.function, m.index.shape[1]
        self.n = n
        v_all = ca.reshape(W[ca.DM(m.index.reshape(-1, order="F"))], m.index.shape[0], n)
        nx, nu = fn.size1_in(0), fn.size1_in(1)
        self.args = [v_all[:nx, :], v_all[nx:nx + nu, :], v_all[nx + nu:, :]]
        self.rows = ca.vec(fn.map(f"{m.block}_map", "serial", n, [3], [])(*self.args, P))
        x, u, xn, p = (ca.SX.sym(fn.name_in(k), fn.sparsity_in(k)) for k in range(4))
        v = ca.vertcat(x, u, xn)
        r = fn(x, u, xn, p)
        lam = ca.SX.sym("lam", r.numel())
        self._jac = ca.Function(f"{m.block}_stage_jac", [x, u, xn, p], [ca.jacobian(r, v)])
        hess = ca.hessian(ca.dot(lam, r), v)[0]
        self._hess = ca.Function(f"{m.block}_stage_hess", [x, u, xn, p, lam], [hess])
        self._grad_p = ca.Function(f"{m.block}_stage_grad_p", [x, u, xn, p, lam],
                                   [ca.gradient(ca.dot(lam, r), p)])
        self.p_enters = ca.jacobian(r, p).nnz() > 0

    def jacobian(self) -> ca.MX:
        """``∂ rows / ∂ W`` (sparse: each stage's block at its variables' columns)."""
        m, nw = self.stage, self.W.numel()
        blocks = self._jac.map(f"{m.block}_jac_map", "serial", self.n, [3], [])(
            *self.args, self.P)
        sp, S = _scatter(self._jac.sparsity_out(0), m.index, (self.rows.numel(), nw), None)
        return ca.MX(sp, ca.mtimes(S, blocks.nz[:]))

    def hessian(self, lam: ca.MX) -> ca.MX:
        """``∇²_W (λᵀ rows)`` (each stage's block at its variables, overlaps summed)."""
        m, nw = self.stage, self.W.numel()
        lam_s = ca.reshape(lam, self.rows.numel() // self.n, self.n)
        blocks = self._hess.map(f"{m.block}_hess_map", "serial", self.n, [3], [])(
            *self.args, self.P, lam_s)
        sp, S = _scatter(self._hess.sparsity_out(0), m.index, (nw, nw), m.index)
        return ca.MX(sp, ca.mtimes(S, blocks.nz[:]))

    def gradient_p(self, lam: ca.MX) -> ca.MX:
        """``∇_P (λᵀ rows)`` (zero when the stages do not read the parameters)."""
        if not self.p_enters:
            return ca.MX(self.P.numel(), 1)
        lam_s = ca.reshape(lam, self.rows.numel() // self.n, self.n)
        return self._grad_p.map(f"{self.stage.block}_grad_p_map", "serial", self.n, [3],
                                [0])(*self.args, self.P, lam_s)


@dataclass(frozen=True)
class CompactNLP:
    """The compact lowering of :func:`compact_nlp`: ``g`` is ``rest_0, mapped_0, rest_1,
    mapped_1, …`` where the ``rest`` rows (sizes :attr:`rest_sizes`) and the cost ``f``
    are SX expressions of ``(w, p)`` and each ``mapped`` piece an MX expression of
    ``(W, P)``, the MX symbols of the same vectors."""

    w: ca.SX
    p: ca.SX
    f: ca.SX
    rest: ca.SX
    rest_sizes: list[int]
    W: ca.MX
    P: ca.MX
    stages: list[MappedStages]

    @property
    def mapped(self) -> list[ca.MX]:
        """The rows of each stage map (MX)."""
        return [s.rows for s in self.stages]

    def _rows(self, *out: ca.MX) -> list[ca.MX]:
        """Interleave the pieces of the rest rows ``out`` (split by :attr:`rest_sizes`)
        with the mapped pieces, in the order of ``g``."""
        parts, k = [], 0
        for j, size in enumerate(self.rest_sizes):
            parts.append(out[0][k:k + size, :] if size else ca.MX(0, out[0].size2()))
            k += size
            if j < len(self.mapped):
                parts.append(out[1][j])
        return parts

    @property
    def nlp(self) -> dict:
        """The ``{x, p, f, g}`` dictionary ``nlpsol`` takes (MX)."""
        f, rest = ca.Function("rows", [self.w, self.p], [self.f, self.rest])(self.W, self.P)
        return {"x": self.W, "p": self.P, "f": f,
                "g": ca.vertcat(*self._rows(rest, self.mapped))}

    def derivatives(self) -> dict[str, ca.Function]:
        """``sqpmethod``'s derivative functions as ``nlpsol`` options (``jac_fg``,
        ``hess_lag``, ``cache`` of ``nlp_fg``/``nlp_grad``: the contract of
        :func:`~balustrade.backends.casadi_backend.shared_derivatives`), with the rest rows
        and the cost differentiated in SX (exact sparse expressions, once) and the mapped
        pieces in MX (maps of the stage's derivatives)."""
        w, p, W, P = self.w, self.p, self.W, self.P
        ng = self.rest.numel() + sum(m.numel() for m in self.mapped)
        lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", ng)
        # the multipliers of the rest rows and of the mapped rows
        lam_parts, k = [], 0
        for j, size in enumerate(self.rest_sizes):
            lam_parts.append(("rest", lam_g[k:k + size]))
            k += size
            if j < len(self.mapped):
                n = self.mapped[j].numel()
                lam_parts.append(("map", lam_g[k:k + n]))
                k += n
        lam_rest = ca.vertcat(ca.MX(0, 1), *[v for t, v in lam_parts if t == "rest"])
        lam_map = [v for t, v in lam_parts if t == "map"]
        sf, sl = ca.SX.sym("lam_f"), ca.SX.sym("lam_rest", self.rest.numel())
        lag = sf * self.f + (ca.dot(sl, self.rest) if self.rest.numel() else 0)
        # one SX function for values and first derivatives (in x and p) of the rest: the
        # Lagrangian's gradient is assembled from it (no second copy of the rows in C)
        rest_jac = ca.Function("rest_jac", [w, p], [
            self.f, ca.gradient(self.f, w), self.rest, ca.jacobian(self.rest, w),
            ca.gradient(self.f, p), ca.jacobian(self.rest, p)])
        rest_hess = ca.Function("rest_hess", [w, p, sf, sl], [ca.hessian(lag, w)[0]])
        f, grad_f, rest, jac_rest, grad_f_p, jac_rest_p = rest_jac(W, P)
        g = ca.vertcat(*self._rows(rest, self.mapped))
        jac_map = [s.jacobian() for s in self.stages]
        jac_g = ca.vertcat(*self._rows(jac_rest, jac_map))
        hess = rest_hess(W, P, lam_f, lam_rest)
        for s, lm in zip(self.stages, lam_map):
            hess = hess + s.hessian(lm)
        grad_x, grad_p = lam_f * grad_f, lam_f * grad_f_p
        if self.rest.numel():
            grad_x = grad_x + ca.mtimes(jac_rest.T, lam_rest)
            grad_p = grad_p + ca.mtimes(jac_rest_p.T, lam_rest)
        for s, jm, lm in zip(self.stages, jac_map, lam_map):
            grad_x = grad_x + ca.mtimes(jm.T, lm)
            grad_p = grad_p + s.gradient_p(lm)
        jac_fg = ca.Function("nlp_jac_fg", [W, P], [f, grad_f, g, jac_g], ["x", "p"],
                             ["f", "grad_f_x", "g", "jac_g_x"])
        hess_lag = ca.Function("nlp_hess_l", [W, P, lam_f, lam_g], [hess],
                               ["x", "p", "lam_f", "lam_g"], ["hess_gamma_x_x"])
        fg = ca.Function("nlp_fg", [W, P], [f, g], ["x", "p"], ["f", "g"])
        grad = ca.Function("nlp_grad", [W, P, lam_f, lam_g], [f, g, grad_x, grad_p],
                           ["x", "p", "lam_f", "lam_g"],
                           ["f", "g", "grad_gamma_x", "grad_gamma_p"])
        return {"jac_fg": jac_fg, "hess_lag": hess_lag,
                "cache": {"nlp_fg": fg, "nlp_grad": grad}}
