"""The last pass of the CasADi chain: a :class:`~balustrade.backends.passes.epigraph.
SmoothProblem` becomes the data ``nlpsol`` takes (:class:`NLPData`): the ``{x, p, f, g}``
dictionary and the numeric bounds and initial point, all read from the one layout."""

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


def compact_nlp(data: NLPData, ocp: OCP) -> dict:
    """``data.nlp`` in the compact lowering: the same ``{x, p, f, g}`` (same variables,
    rows and values) built in MX, with each dynamics block one SX stage function
    ``Function.map``-ped over the horizon (:func:`dynamics_stage_map`) and every other row
    and the cost one SX function of ``(w, p)``.

    Why (issue #14 §3): in the expanded SX lowering the derivatives of ``g`` are written
    out for every stage (the cart-pole PCBF problem, RK4, N = 20: 2.1 MB of C). In MX the
    Jacobian of a map is a map of the stage's directional derivatives and the Hessian of
    the Lagrangian a map of its forward-over-reverse derivative, so each appears once in
    the generated code. Blocks that are not a clean stage map stay in the SX function."""
    w, p, f, g = (data.nlp[k] for k in ("x", "p", "f", "g"))
    maps = [m for b in ocp.blocks if b.tag == BlockTag.DYNAMICS
            for m in [dynamics_stage_map(data, ocp, b)] if m is not None]
    maps.sort(key=lambda m: m.rows.start)
    W, P = ca.MX.sym("w", w.numel()), ca.MX.sym("p", p.numel())
    cuts = [0, *[k for m in maps for k in (m.rows.start, m.rows.stop)], g.numel()]
    rest_rows = [g[cuts[2 * j]: cuts[2 * j + 1]] for j in range(len(maps) + 1)]
    rest = ca.Function("rows", [w, p], [f, *rest_rows])
    f_mx, *pieces = rest(W, P)
    g_parts = [pieces[0]]
    for m, after in zip(maps, pieces[1:]):
        n = m.index.shape[1]
        mapped = m.function.map(f"{m.block}_map", "serial", n, [3], [])
        stage_vars = ca.reshape(W[ca.DM(m.index.reshape(-1, order="F"))],
                                m.index.shape[0], n)
        nx = m.function.size1_in(0)
        nu = m.function.size1_in(1)
        r = mapped(stage_vars[:nx, :], stage_vars[nx:nx + nu, :], stage_vars[nx + nu:, :], P)
        g_parts += [ca.vec(r), after]
    return {"x": W, "p": P, "f": f_mx, "g": ca.vertcat(*g_parts)}
