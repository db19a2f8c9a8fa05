"""The stage-order pass: an :class:`~balustrade.backends.passes.casadi_nlp.NLPData` of a
horizon OCP rewritten stage by stage for CasADi's structure-exploiting solvers (issue #14 §2).

``fatrop`` (interior point) and ``hpipm`` (the QP solver inside ``sqpmethod``) take the
decision vector ordered ``[x_0, u_0, x_1, u_1, …, x_N, u_N]`` and the constraint rows
ordered ``[gap_0, path_0, gap_1, path_1, …, path_N]``, where the gap rows of stage ``k``
are ``x_{k+1} − F_k(x_k, u_k) = 0`` (one per state of stage ``k+1``, in the states' order:
the Jacobian block on ``x_{k+1}`` is the identity) and the path rows of stage ``k`` depend
on ``(x_k, u_k)`` only; the Lagrangian Hessian must be block diagonal by stage. The
per-stage sizes ``nx``, ``nu``, ``ng`` are passed as solver options
(:meth:`StagedNLP.structure`).

How each part of a balustrade horizon OCP is placed (the lifted problem is *equivalent*:
same feasible set and optimum after :meth:`StageInverse.primal`):

* a state variable (role ``state``, shape ``(n, N+1)``): column ``k`` is the state of
  stage ``k``; its dynamics block (tag ``dynamics``, column ``k`` = ``x_{k+1} − f(x_k,
  u_k)``, :meth:`~balustrade.dsl.ocp.OCP.dynamics`) gives the gap rows of stage ``k``;
* any other variable with ``N`` or ``N+1`` columns (inputs ``u``/``v``, slacks ``ξ``):
  column ``k`` is a control of stage ``k``;
* every other block (scalars such as ``ξ_N`` or ``t`` of (7.8), epigraph variables of
  norm costs) is an *extra*: when all rows using it lie in one stage it is a control of
  that stage (an extra in no row and not in the cost, e.g. the fixed ``ξ_N ≡ 0`` of the
  obstacle car's (2.24), is a control of stage 0); otherwise it is *lifted*: one copy
  ``e_k`` per stage, a state chained by the gap rows ``e_{k+1} − e_k = 0``, each row
  using the copy of its own stage, the extra's bounds on the copy of stage ``N`` (which
  is the value reported);
* a row whose variables lie in one stage is a path row of that stage; a row over several
  stages that is additively separable by stage (its Hessian has no cross-stage entry, e.g.
  the decrease constraint (6.15g) ``α_f ξ_N + Σ_i 1ᵀξ_i <= bound`` or the perspective row of
  a 2-norm slack cost) ``r = c + Σ_k r_k(w_k)`` becomes a running sum ``σ``: a state with
  ``σ_0 = 0`` (a path row of stage 0), gap rows ``σ_{k+1} = σ_k + r_k(w_k)`` and the path row
  ``σ_N + r_N(w_N) + c`` of stage ``N`` with the original bounds (its multiplier is the
  original row's);
* the cost must be additively separable by stage too; it is split the same way.

Anything else (a dynamics row that is not ``x_{k+1} − f(x_k, u_k)``, a cost or row coupling
stages non-separably such as a rate cost ``‖u_k − u_{k−1}‖``) is refused with a
:class:`StructureError` naming the block.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from balustrade.backends.passes.casadi_nlp import NLPData
from balustrade.dsl.ocp import OCP, BlockTag, VariableRole
from balustrade.errors import BalustradeError


class StructureError(BalustradeError):
    """An OCP whose structure cannot be ordered stage by stage (the message names the
    block)."""


@dataclass
class _Stage:
    states: list = field(default_factory=list)     # SX scalars, in order
    controls: list = field(default_factory=list)
    gap: list = field(default_factory=list)        # (state SX, row expr, source row or -1)
    path: list = field(default_factory=list)       # (row expr, lb, ub, source row or -1)


@dataclass(frozen=True)
class StageInverse:
    """Maps between the staged problem and the original :class:`NLPData`.

    ``take``: ``w_all = w_staged[take]`` (the original decision vector, epigraph blocks
    included; a lifted extra reads its copy of stage ``N``) and the bound multipliers
    likewise; ``row_take``: ``lam_g = lam_g_staged[row_take]`` (a split row reads its last
    row); ``lift``: ``(w_all, p) ↦ w_staged`` (copies and running sums filled in)."""

    take: np.ndarray
    row_take: np.ndarray
    lift: ca.Function

    def primal(self, w_staged: np.ndarray) -> np.ndarray:
        return np.asarray(w_staged).reshape(-1)[self.take]

    def row_dual(self, lam_g_staged: np.ndarray) -> np.ndarray:
        return np.asarray(lam_g_staged).reshape(-1)[self.row_take]

    def staged(self, w_all: np.ndarray, p: np.ndarray) -> np.ndarray:
        return np.asarray(self.lift(w_all, p)).reshape(-1)


@dataclass(frozen=True)
class StagedNLP:
    """The stage-ordered problem: ``nlp`` (``x``/``p``/``f``/``g``), its bounds, the initial
    point and the per-stage sizes ``nx``, ``nu``, ``ng`` (each of length ``N + 1``)."""

    nlp: dict
    lbx: np.ndarray
    ubx: np.ndarray
    lbg: np.ndarray
    ubg: np.ndarray
    x0: np.ndarray
    N: int
    nx: tuple[int, ...]
    nu: tuple[int, ...]
    ng: tuple[int, ...]

    def structure(self, solver: str) -> dict:
        """The structure options of ``solver``: for ``fatrop`` (``nlpsol``)
        ``structure_detection='manual'`` with ``N``/``nx``/``nu``/``ng``; for ``hpipm``
        (``qpsol_options`` of ``sqpmethod``) ``N``/``nx``/``nu``/``ng`` (CasADi 3.8 asserts
        ``len(nu) == N + 1`` although its documentation says ``N``)."""
        sizes = {"N": self.N, "nx": list(self.nx), "nu": list(self.nu), "ng": list(self.ng)}
        if solver == "fatrop":
            return {"structure_detection": "manual", **sizes}
        if solver == "hpipm":
            return sizes
        raise StructureError(f"no stage-structure options known for solver {solver!r}")


def _stage_of_columns(ocp: OCP, data: NLPData) -> tuple[dict[int, tuple[int, str]], list]:
    """``element index -> (stage, 'x'|'u')`` for staged variables, and the extras as lists
    of element indices (one list per layout block)."""
    N = ocp.N
    staged: dict[int, tuple[int, str]] = {}
    extras = []
    for e in data.layout.entries:
        rows, cols = e.shape
        var = ocp.variables.get(e.name) if e.origin == "user" else None
        is_state = var is not None and var.role == VariableRole.STATE and cols == N + 1
        if var is not None and cols in (N, N + 1) and N > 1:
            for c in range(cols):
                for r in range(rows):
                    staged[e.slice.start + c * rows + r] = (c, "x" if is_state else "u")
        else:
            extras.append(list(range(e.slice.start, e.slice.stop)))
    return staged, extras


def stage_order(ocp: OCP, data: NLPData, last_controls: bool = True
                ) -> tuple[StagedNLP, StageInverse]:
    """``data`` (the CasADi chain's output for ``ocp``) in stage order (module docstring).
    ``last_controls=False`` (HPIPM): no controls in stage ``N``; an extra used only there is
    lifted instead."""
    if ocp.system is None or ocp.N < 2:
        raise StructureError(f"{ocp.name}: stage ordering needs a horizon OCP (a system and "
                             f"N >= 2), got N = {ocp.N}")
    N = ocp.N
    w, p, f, g = data.nlp["x"], data.nlp["p"], data.nlp["f"], data.nlp["g"]
    n, m = int(w.numel()), int(g.numel())
    wel = [w[i] for i in range(n)]
    staged, extra_blocks = _stage_of_columns(ocp, data)
    stage_arr = np.full(n, -1)
    for i, (k, _) in staged.items():
        stage_arr[i] = k
    block_of_row = np.empty(m, dtype=object)
    tag_of_row = np.empty(m, dtype=object)
    for b in ocp.blocks:
        s = data.block_rows[b.name]
        block_of_row[s] = b.name
        tag_of_row[s] = b.tag
    block_of_row[data.n_g_user:] = "cost epigraph rows"
    tag_of_row[data.n_g_user:] = BlockTag.GENERIC

    rr, cc = ca.jacobian(g, w).sparsity().get_triplet()
    rr, cc = np.asarray(rr, dtype=int), np.asarray(cc, dtype=int)
    order = np.argsort(rr, kind="stable")
    bounds = np.searchsorted(rr[order], np.arange(m + 1))
    row_vars = [cc[order[bounds[j]:bounds[j + 1]]] for j in range(m)]

    # -- extras: a control of one stage, or lifted to one copy per stage -----------------
    extra_index = {i: b for b, blk in enumerate(extra_blocks) for i in blk}
    rows_of_extra: dict[int, set] = {i: set() for i in extra_index}
    for j in range(m):
        for i in row_vars[j]:
            if i in rows_of_extra:
                rows_of_extra[i].add(j)
    extra_stage: dict[int, int] = {}
    lifted: list[int] = []
    for i in extra_index:
        if tag_of_row[list(rows_of_extra[i])].tolist().count(BlockTag.DYNAMICS) \
                if rows_of_extra[i] else False:
            raise StructureError(f"{ocp.name}: variable element {i} ({_block_name(data, i)}) "
                                 "enters the dynamics; it cannot be ordered by stage")
        stages = {int(stage_arr[v]) for j in rows_of_extra[i] for v in row_vars[j]
                  if stage_arr[v] >= 0}
        if not rows_of_extra[i] and not ca.depends_on(f, wel[i]):
            stages = {0}  # in no row and not in the cost (only bounds): couples no stage
        if len(stages) == 1 and (last_controls or N not in stages):
            extra_stage[i] = stages.pop()
        else:
            lifted.append(i)
    copies = {i: [ca.SX.sym(f"{_block_name(data, i)}_{i}_c{k}") for k in range(N + 1)]
              for i in lifted}

    stages = [_Stage() for _ in range(N + 1)]
    x_of_stage: list[list[int]] = [[] for _ in range(N + 1)]
    for i in range(n):
        if i in staged:
            k, kind = staged[i]
            (stages[k].states if kind == "x" else stages[k].controls).append(wel[i])
            if kind == "x":
                x_of_stage[k].append(i)
        elif i in extra_stage:
            stages[extra_stage[i]].controls.append(wel[i])
    for i in lifted:
        for k in range(N + 1):
            stages[k].states.append(copies[i][k])
        for k in range(N):
            stages[k].gap.append((copies[i][k + 1], copies[i][k + 1] - copies[i][k], -1))

    lbg, ubg = data.lbg, data.ubg
    lifted_syms = [wel[i] for i in lifted]

    def at_stage(expr: ca.SX, k: int) -> ca.SX:
        if not lifted:
            return expr
        return ca.substitute(expr, ca.vertcat(*lifted_syms),
                             ca.vertcat(*[copies[i][k] for i in lifted]))


    def split(expr: ca.SX, what: str) -> tuple[list[ca.SX], ca.SX]:
        """``expr = c + Σ_k r_k(w_k)`` → ``([r_0, …, r_N], c)`` (lifted extras per stage)."""
        _check_separable(expr, w, stage_arr, f"{ocp.name}: {what}")
        zero_all = ca.substitute(expr, ca.vertcat(*[wel[i] for i in staged]),
                                 ca.DM.zeros(len(staged)))
        parts = []
        for k in range(N + 1):
            others = [wel[i] for i in staged if stage_arr[i] != k]
            parts.append(ca.substitute(expr, ca.vertcat(*others), ca.DM.zeros(len(others)))
                         - zero_all)
        _check_split(expr, parts, zero_all, w, p, f"{ocp.name}: {what}")
        return [at_stage(rk, k) for k, rk in enumerate(parts)], at_stage(zero_all, N)

    sigma_init: list[tuple[ca.SX, ca.SX]] = []  # (sigma symbol, its value in original vars)
    dyn_by_state: dict[int, tuple[ca.SX, int]] = {}
    for j in range(m):
        expr = g[j]
        vs = row_vars[j]
        row_stages = sorted({int(stage_arr[v]) for v in vs if stage_arr[v] >= 0})
        if tag_of_row[j] == BlockTag.DYNAMICS:
            nxt = [v for v in vs if stage_arr[v] == (row_stages[-1] if row_stages else -1)]
            ok = (len(row_stages) == 2 and row_stages[1] == row_stages[0] + 1
                  and len(nxt) == 1 and nxt[0] in x_of_stage[row_stages[1]]
                  and lbg[j] == 0.0 and ubg[j] == 0.0
                  # the gap rows' Jacobian block on x_(k+1) must be the identity
                  and ca.jacobian(expr, wel[int(nxt[0])]).is_one())
            if not ok:
                raise StructureError(
                    f"{ocp.name}: dynamics block {block_of_row[j]!r}: row {j} is not of the "
                    f"form x_(k+1) - f(x_k, u_k) = 0 with coefficient 1 on x_(k+1) (stages "
                    f"{row_stages})")
            dyn_by_state[int(nxt[0])] = (expr, j)
            continue
        if len(row_stages) <= 1:
            k = row_stages[0] if row_stages else N
            stages[k].path.append((at_stage(expr, k), lbg[j], ubg[j], j))
            continue
        parts, const = split(expr, f"block {block_of_row[j]!r} (row {j})")
        sig = [ca.SX.sym(f"sigma{j}_{k}") for k in range(N + 1)]
        for k in range(N + 1):
            stages[k].states.append(sig[k])
        for k in range(N):
            stages[k].gap.append((sig[k + 1], sig[k + 1] - sig[k] - parts[k], -1))
        stages[0].path.append((sig[0], 0.0, 0.0, -1))
        stages[N].path.append((sig[N] + parts[N] + const, lbg[j], ubg[j], j))
        # running sums in the original variables (for initial points)
        orig_parts, _ = _orig_parts(expr, wel, staged, stage_arr, N)
        acc = ca.SX(0)
        for k in range(N + 1):
            sigma_init.append((sig[k], acc))
            acc = acc + orig_parts[k]

    # dynamics gap rows in the order of the states of stage k+1
    for k in range(N):
        dyn = [(wel[i], *dyn_by_state[i]) for i in x_of_stage[k + 1] if i in dyn_by_state]
        missing = [i for i in x_of_stage[k + 1] if i not in dyn_by_state]
        if missing:
            raise StructureError(f"{ocp.name}: no dynamics row defines state element "
                                 f"{missing[0]} ({_block_name(data, missing[0])}) of stage "
                                 f"{k + 1}")
        stages[k].gap[:0] = [(s, at_stage(e, k), j) for s, e, j in dyn]

    # the cost, split by stage
    f_parts, f_const = split(f, "the cost") if _couples(f, w, stage_arr) or lifted \
        else ([f] + [ca.SX(0)] * N, ca.SX(0))

    # -- assemble -------------------------------------------------------------------
    xs, gs, lb_g, ub_g, row_take = [], [], [], [], np.zeros(m, dtype=int)
    nx, nu, ng = [], [], []
    for k, st in enumerate(stages):
        xs += st.states + st.controls
        nx.append(len(st.states))
        nu.append(len(st.controls))
        if k < N:
            nxt_states = stages[k + 1].states
            if [s for s, _, _ in st.gap] != nxt_states[:len(st.gap)] \
                    or len(st.gap) != len(nxt_states):
                raise StructureError(f"{ocp.name}: the gap rows of stage {k} do not match "
                                     f"the states of stage {k + 1}")
            for _, e, j in st.gap:
                if j >= 0:
                    row_take[j] = len(gs)
                gs.append(e)
                lb_g.append(0.0)
                ub_g.append(0.0)
        ng.append(len(st.path))
        for e, lo, hi, j in st.path:
            if j >= 0:
                row_take[j] = len(gs)
            gs.append(e)
            lb_g.append(lo)
            ub_g.append(hi)
    w_new = ca.vertcat(*xs)
    pos = {s.element_hash(): q for q, s in enumerate(xs)}
    take = np.array([pos[copies[i][N].element_hash()] if i in copies
                     else pos[wel[i].element_hash()] for i in range(n)], dtype=int)
    lbx0, ubx0 = data.lbx, data.ubx
    lbx, ubx = np.full(len(xs), -np.inf), np.full(len(xs), np.inf)
    lbx[take], ubx[take] = lbx0, ubx0
    f_new = sum((f_parts[k] for k in range(N + 1)), f_const)
    g_new = ca.vertcat(*gs)
    subs_from = [c for i in lifted for c in copies[i]] + [s for s, _ in sigma_init]
    subs_to = [wel[i] for i in lifted for _ in range(N + 1)] + [v for _, v in sigma_init]
    w_lift = ca.substitute(w_new, ca.vertcat(*subs_from), ca.vertcat(*subs_to)) \
        if subs_from else w_new
    lift = ca.Function("stage_lift", [w, p], [w_lift])
    x0 = np.asarray(lift(data.x0, np.zeros(int(p.numel())))).reshape(-1)
    staged_nlp = StagedNLP({"x": w_new, "p": p, "f": f_new, "g": g_new}, lbx, ubx,
                           np.asarray(lb_g, dtype=float), np.asarray(ub_g, dtype=float), x0, N,
                           tuple(nx), tuple(nu), tuple(ng))
    _check_hessian(staged_nlp, ocp.name)
    return staged_nlp, StageInverse(take, row_take, lift)


def staged_compact(compact: object, inverse: StageInverse
                   ) -> tuple[dict, dict[str, dict[str, ca.Function]]]:
    """The compact lowering (:class:`~balustrade.backends.passes.casadi_nlp.CompactNLP`:
    each dynamics block one stage function mapped over the horizon, its derivatives written
    once) of a problem whose stage order *permutes* the layout (no lifted copies or running
    sums: ``inverse.take`` and ``inverse.row_take`` are permutations): ``(nlp, caches)``
    with the MX ``{x, p, f, g}`` in stage order and, per solver plugin (``fatrop``,
    ``ipopt``), the derivative functions its ``nlpsol`` looks up by name in the ``cache``
    option, built from the compact ones and permuted (same values as the expanded NLP's).

    Why (issue #14): in the expanded SX NLP fatrop's Hessian, Jacobian and Lagrangian
    gradient are every stage's RK4 derivative written out (the cart-pole pair: 4.7 MB of
    C with the IPOPT retries)."""
    take = np.asarray(inverse.take, dtype=int)
    rows = np.asarray(inverse.row_take, dtype=int)
    n, m = take.size, rows.size
    if not (np.array_equal(np.sort(take), np.arange(n))
            and np.array_equal(np.sort(rows), np.arange(m))):
        raise StructureError("the compact lowering of a stage-ordered problem needs a stage "
                             "order that permutes the layout (no lifted copies or sums)")
    inv_x, inv_g = np.empty(n, dtype=int), np.empty(m, dtype=int)
    inv_x[take], inv_g[rows] = np.arange(n), np.arange(m)
    d = compact.derivatives()
    jac_fg, hess_lag, grad = d["jac_fg"], d["hess_lag"], d["cache"]["nlp_grad"]
    ws, ps = ca.MX.sym("x", n), ca.MX.sym("p", compact.P.numel())
    lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", m)
    wl, lg = ws[ca.DM(take)], lam_g[ca.DM(rows)]
    ix, ig = ca.DM(inv_x), ca.DM(inv_g)
    f, grad_f, g, jac_g = jac_fg(wl, ps)
    grad_f, g, jac_g = grad_f[ix], g[ig], jac_g[ig, ix]
    hess = hess_lag(wl, ps, lam_f, lg)[ix, ix]
    _, _, grad_x, grad_p = grad(wl, ps, lam_f, lg)
    grad_x = grad_x[ix]
    xp, xpl = ["x", "p"], ["x", "p", "lam_f", "lam_g"]
    common = {
        "nlp_f": ca.Function("nlp_f", [ws, ps], [f], xp, ["f"]),
        "nlp_g": ca.Function("nlp_g", [ws, ps], [g], xp, ["g"]),
        "nlp_jac_g": ca.Function("nlp_jac_g", [ws, ps], [g, jac_g], xp, ["g", "jac_g_x"]),
        "nlp_grad": ca.Function("nlp_grad", [ws, ps, lam_f, lam_g], [f, g, grad_x, grad_p],
                                xpl, ["f", "g", "grad_gamma_x", "grad_gamma_p"]),
    }
    fatrop = {**common,
              "nlp_grad_f": ca.Function("nlp_grad_f", [ws, ps], [grad_f], xp, ["grad_f_x"]),
              "nlp_hess_l": ca.Function("nlp_hess_l", [ws, ps, lam_f, lam_g], [grad_x, hess],
                                        xpl, ["grad_gamma_x", "hess_gamma_x_x"])}
    ipopt = {**common,
             "nlp_grad_f": ca.Function("nlp_grad_f", [ws, ps], [f, grad_f], xp,
                                       ["f", "grad_f_x"]),
             "nlp_hess_l": ca.Function("nlp_hess_l", [ws, ps, lam_f, lam_g], [ca.triu(hess)],
                                       xpl, ["triu_hess_gamma_x_x"])}
    nlp = {"x": ws, "p": ps, "f": f, "g": g}
    return nlp, {"fatrop": fatrop, "ipopt": ipopt}


def _orig_parts(expr: ca.SX, wel: list, staged: dict, stage_arr: np.ndarray, N: int
                ) -> tuple[list[ca.SX], ca.SX]:
    idx = list(staged)
    zero_all = ca.substitute(expr, ca.vertcat(*[wel[i] for i in idx]), ca.DM.zeros(len(idx)))
    parts = []
    for k in range(N + 1):
        others = [wel[i] for i in idx if stage_arr[i] != k]
        parts.append(ca.substitute(expr, ca.vertcat(*others), ca.DM.zeros(len(others)))
                     - zero_all)
    return parts, zero_all


def _couples(expr: ca.SX, w: ca.SX, stage_arr: np.ndarray) -> bool:
    """Whether ``expr``'s Hessian has an entry between two different stages."""
    h = ca.hessian(expr, w)[0].sparsity()
    r, c = h.get_triplet()
    r, c = np.asarray(r, dtype=int), np.asarray(c, dtype=int)
    sr, sc = stage_arr[r], stage_arr[c]
    return bool(np.any((sr >= 0) & (sc >= 0) & (sr != sc)))


def _check_separable(expr: ca.SX, w: ca.SX, stage_arr: np.ndarray, what: str) -> None:
    if _couples(expr, w, stage_arr):
        raise StructureError(f"{what} couples variables of different stages non-separably "
                             "(a cross-stage Hessian entry, e.g. a rate cost or a norm over "
                             "several stages); it cannot be ordered by stage")


def _check_split(expr: ca.SX, parts: list[ca.SX], const: ca.SX, w: ca.SX, p: ca.SX,
                 what: str, points: int = 5) -> None:
    """``expr == const + Σ_k parts[k]`` at a few random points: the Hessian test of
    :func:`_check_separable` cannot see a cross-stage coupling through a piecewise
    constant/linear function (``sign``, ``if_else``: structurally zero second derivatives),
    which the split would silently replace by another function."""
    size = ca.fabs(expr) + ca.fabs(const) + ca.sum1(ca.fabs(ca.vertcat(*parts)))
    f = ca.Function("split_check", [w, p], [expr - const - sum(parts, ca.SX(0)), size])
    rng = np.random.default_rng(0)
    for _ in range(points):
        gap, scale = (float(v) for v in f(rng.standard_normal(int(w.numel())),
                                          rng.standard_normal(int(p.numel()))))
        # (a point outside the functions' domain, e.g. log of a negative, says nothing)
        if np.isfinite(scale) and not abs(gap) <= 1e-8 * (1.0 + scale):
            raise StructureError(f"{what} is not additively separable by stage (its split "
                                 f"by stage differs by {gap:.3g} at a test point: a "
                                 "coupling through sign/if_else or similar); it cannot be "
                                 "ordered by stage")


def _check_hessian(nlp: StagedNLP, name: str) -> None:
    """The Lagrangian Hessian of the staged problem is block diagonal by stage."""
    w, g = nlp.nlp["x"], nlp.nlp["g"]
    lam = ca.SX.sym("lam", g.numel())
    h = ca.hessian(nlp.nlp["f"] + ca.dot(lam, g), w)[0].sparsity()
    stage_of = np.repeat(np.arange(nlp.N + 1), np.add(nlp.nx, nlp.nu))
    r, c = h.get_triplet()
    bad = np.nonzero(stage_of[np.asarray(r, dtype=int)] != stage_of[np.asarray(c, dtype=int)])[0]
    if bad.size:
        raise StructureError(f"{name}: the staged Lagrangian Hessian couples stages "
                             f"{stage_of[r[bad[0]]]} and {stage_of[c[bad[0]]]}")


def _block_name(data: NLPData, i: int) -> str:
    for e in data.layout.entries:
        if e.slice.start <= i < e.slice.stop:
            return e.name.replace(":", "_")
    return "w"


__all__ = ["StageInverse", "StagedNLP", "StructureError", "stage_order", "staged_compact"]
