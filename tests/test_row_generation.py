"""Row generation (balustrade/backends/row_generation.py): the same answer as the full solve
of a QP with grouped rows (a random QP, the 3-mass (4.5) of Algorithm 4.1), the full-row check
matters, and an infeasible relaxation is reported infeasible with a certificate of the full
problem."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from balustrade.backends import compile
from balustrade.backends.direct_backend import DirectCompiled
from balustrade.backends.solution import Status
from balustrade.dsl import OCP, squared_norm
from balustrade.errors import BalustradeError

ROWGEN = {"row_generation": True}


def _grouped_qp(seed: int = 0, n: int = 6, groups: int = 8, per_group: int = 12,
                infeasible: bool = False) -> OCP:
    """``min ‖y − c‖²`` over ``groups`` blocks of ``per_group`` random halfspaces
    ``a_rᵀ y <= 1 + g_r`` (each block one group), plus ``|y| <= 3`` (ungrouped)."""
    rng = np.random.default_rng(seed)
    ocp = OCP(name=f"grouped{seed}")
    y = ocp.variable("y", n)
    c = ocp.parameter("c", n)
    marks = {}
    for g in range(groups):
        a = rng.normal(size=(per_group, n))
        h = 1.0 + rng.uniform(0.0, 0.5, per_group)
        if infeasible and g == groups - 1:     # y_0 >= 1 and y_0 <= -1, in one group
            a = np.zeros((2, n))
            a[0, 0], a[1, 0] = -1.0, 1.0
            h = np.array([-1.0, -1.0])
        ocp.le(ca.mtimes(ca.DM(a), y), ca.DM(h), name=f"group_{g}")
        marks[f"group_{g}"] = np.full(a.shape[0], g)
    ocp.le(y, 3.0, name="upper")
    ocp.le(-y, 3.0, name="lower")
    ocp.minimize(squared_norm(y - c))
    ocp.row_groups = marks
    return ocp


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_grouped_qp_equals_full_solve(seed):
    ocp = _grouped_qp(seed)
    full, gen = DirectCompiled(ocp, "piqp"), DirectCompiled(ocp, "piqp", ROWGEN)
    assert gen.rowgen is not None and full.rowgen is None
    rng = np.random.default_rng(100 + seed)
    rounds = []
    for _ in range(6):
        c = rng.normal(scale=4.0, size=6)
        a, b = full.solve({"c": c}), gen.solve({"c": c})
        assert a.status == b.status == Status.OPTIMAL
        # 1e-7: at the vertex optima of these random polytopes (6 rows active in 6
        # dimensions) each interior-point solve is itself only 5e-8 from the active-set
        # KKT solution (measured for both, full and generated); on (4.5) below: 1e-8
        assert np.max(np.abs(a.primal["y"] - b.primal["y"])) < 1e-7
        assert abs(a.objective - b.objective) < 1e-7
        for name in ("group_0", "upper"):      # multipliers of the full QP, zeros included
            assert np.allclose(a.dual[name], b.dual[name], atol=1e-6)
        rounds.append(gen.rowgen.stats.rounds)
        assert gen.rowgen.stats.rows < 8 * 12 + 12     # fewer rows than the full QP
    assert max(rounds) > 1                     # rows were generated, not all seeded


def test_first_round_alone_violates_a_row():
    """Without the check of every row after a round, the reduced optimum is not feasible:
    the check is what makes row generation exact."""
    ocp = _grouped_qp(0)
    gen = DirectCompiled(ocp, "piqp", ROWGEN)
    rg, prog = gen.rowgen, gen.program
    p = ocp.pack_parameters({"c": np.full(6, 4.0)})
    q, b = prog.q(p), prog.b(p)
    A_eq, G = rg._split(prog.A_data(p))
    h = b[rg.m0:]
    rows = np.flatnonzero(rg._initial(h))
    first, _ = rg._solve_reduced(q, A_eq, b[:rg.m0], G[rows], h[rows])
    assert first.status == Status.OPTIMAL
    assert np.max(G @ first.y - h) > 1e-3      # a row of the full QP is violated
    done = rg.run(q, b, prog.A_data(p), cold=True)
    assert done.status == Status.OPTIMAL and rg.stats.rounds > 1
    assert np.max(G @ done.y - h) < 1e-8


def test_infeasible_relaxation_is_infeasible():
    ocp = _grouped_qp(3, infeasible=True)
    full, gen = DirectCompiled(ocp, "piqp"), DirectCompiled(ocp, "piqp", ROWGEN)
    a, b = full.solve({"c": np.zeros(6)}), gen.solve({"c": np.zeros(6)})
    assert a.status == b.status == Status.INFEASIBLE
    # the verdict comes from a relaxation (row generation did not fall back to the full
    # QP) ...
    assert "a relaxation with" in b.message and "the full QP;" not in b.message
    assert gen.rowgen.stats.rows < 8 * 12 + 12
    # ... and what establishes it is the Clarabel feasibility solve of the full constraints,
    # whose certificate passes the Farkas check on the full data: PIQP's certificate of the
    # relaxation, extended by zeros, does not (‖Aᵀz‖₁ 4e-7 .. 8e-5 measured for seeds 0–5:
    # it excludes feasible points only up to ‖y‖∞ 2e4 .. 5e5, the check asks for 3e6)
    assert "its certificate does not hold" in b.message
    assert "the clarabel feasibility solve's certificate does" in b.message


def test_unconfirmed_infeasible_relaxation_solves_the_full_qp(monkeypatch):
    """A relaxation's "infeasible" that the checks on the full data overturn (here: made up
    for a feasible QP, no certificate) is not the answer: the full QP is solved."""
    from balustrade.backends.direct_engines import RawResult

    ocp = _grouped_qp(1)
    gen = DirectCompiled(ocp, "piqp", ROWGEN)
    ref = DirectCompiled(ocp, "piqp").solve({"c": np.full(6, 4.0)})

    def says_infeasible(q, b, A=None, cold=False):
        return RawResult(Status.INFEASIBLE, "PIQP: made up (a relaxation)", None, None, 3)

    monkeypatch.setattr(gen.rowgen, "run", says_infeasible)
    sol = gen.solve({"c": np.full(6, 4.0)})
    assert sol.status == Status.OPTIMAL and "the full QP" in sol.message
    assert "the constraints alone are feasible" in sol.message
    assert np.max(np.abs(sol.primal["y"] - ref.primal["y"])) < 1e-8


def test_optimal_missing_a_full_row_solves_the_full_qp(monkeypatch):
    """Row generation's "optimal" comes from reduced solves the engines' row check never
    sees (review R1, session 15): a point that misses a full row by 1e-3 in the row's own
    unit (made up here) is not the answer; the full QP is solved and checked instead."""

    ocp = _grouped_qp(1)
    gen = DirectCompiled(ocp, "piqp", ROWGEN)
    ref = DirectCompiled(ocp, "piqp").solve({"c": np.full(6, 4.0)})
    real = gen.rowgen.run

    def misses_a_row(q, b, A=None, cold=False):
        raw = real(q, b, A)
        raw.y = raw.y + 1e-2                     # rows of norm ~1, |b| ~1: misses ≥ 1e-3
        return raw

    monkeypatch.setattr(gen.rowgen, "run", misses_a_row)
    sol = gen.solve({"c": np.full(6, 4.0)})
    assert sol.status == Status.OPTIMAL and "the full QP" in sol.message
    assert "missed by" in sol.message
    assert np.max(np.abs(sol.primal["y"] - ref.primal["y"])) < 1e-8


def test_failed_round_falls_back_to_the_full_solve():
    ocp = _grouped_qp(1)
    gen = DirectCompiled(ocp, "piqp", ROWGEN)
    gen.rowgen.max_rounds = 1                   # give up after one round
    ref = DirectCompiled(ocp, "piqp").solve({"c": np.full(6, 4.0)})
    sol = gen.solve({"c": np.full(6, 4.0)})
    assert sol.status == Status.OPTIMAL and "the full QP" in sol.message
    assert np.max(np.abs(sol.primal["y"] - ref.primal["y"])) < 1e-8


def test_no_groups_no_row_generation():
    ocp = _grouped_qp(0)
    del ocp.row_groups
    assert DirectCompiled(ocp, "piqp", ROWGEN).rowgen is None


def test_rapsf_three_masses_equals_full_solve():
    """(4.5) of the 3-mass design at the first closed-loop states: the preset
    ``fast-convex-rowgen`` gives the full solve's ``v_0`` within 1e-8."""
    from balustrade.reproduce import msd_adaptive
    from benchmarks.bench_rapsf import Loop

    d = msd_adaptive.design(3)
    ctrl = msd_adaptive.adaptive_controller(d, target="fast-convex")
    loop = Loop(d, ctrl.step, 6)
    states = []
    for k in range(6):
        states.append((loop.x.copy(), k))
        loop(k)
    compiled = next(c for key, c in ctrl._compiled.items() if key[0] == ctrl.N)
    gen = compile(compiled.ocp, "fast-convex-rowgen")
    assert gen.rowgen is not None
    n_th = ctrl._n_compiled if ctrl._n_compiled else len(ctrl.vertices)
    rounds = []
    for x, k in states:
        from benchmarks.bench_rapsf import msd_performance
        idx = np.arange(max(n_th, len(ctrl.vertices))) % len(ctrl.vertices)
        params = {"x0": x, "u_p": msd_performance(k, x, d["n"]),
                  "theta": ctrl.vertices[idx].T, "s": ctrl._s[:, idx]}
        a, b = compiled.solve(params), gen.solve(params)
        assert a.status == b.status == Status.OPTIMAL
        assert np.max(np.abs(a.primal["v"][:, 0] - b.primal["v"][:, 0])) < 1e-8
        rounds.append(gen.rowgen.stats.rounds)
    assert max(rounds) > 1


def test_rapsf_chooses_row_generation_by_size(monkeypatch):
    """RAPSF compiles (4.5) for row generation only from ROWGEN_MIN_ROWS grouped rows on (the
    3-mass problem is below it); forced on, the closed loop applies the same inputs."""
    import balustrade.control.rapsf as rapsf_mod
    from balustrade.reproduce import msd_adaptive
    from benchmarks.bench_rapsf import Loop

    d = msd_adaptive.design(3)
    plain = msd_adaptive.adaptive_controller(d, target="fast-convex")
    loop_plain = Loop(d, plain.step, 8)
    for k in range(8):
        loop_plain(k)
    assert all(getattr(c, "rowgen", None) is None for c in plain._compiled.values())
    monkeypatch.setattr(rapsf_mod, "ROWGEN_MIN_ROWS", 1)
    forced = msd_adaptive.adaptive_controller(d, target="fast-convex")
    loop_forced = Loop(d, forced.step, 8)
    for k in range(8):
        loop_forced(k)
    assert any(getattr(c, "rowgen", None) is not None for c in forced._compiled.values())
    assert np.max(np.abs(np.array(loop_plain.applied) - np.array(loop_forced.applied))) < 1e-8
    assert loop_forced.fallbacks == loop_plain.fallbacks == 0


def test_unknown_kkt_solver_named():
    ocp = _grouped_qp(0)
    gen = DirectCompiled(ocp, "piqp", {"row_generation": {
        "reduced_options": {"kkt_solver": "no_such_kkt"}}})
    with pytest.raises(BalustradeError, match="no_such_kkt"):
        gen.solve({"c": np.zeros(6)})


def test_violation_tolerance_is_the_reduced_solves():
    """A row counts as violated above the tolerance the reduced solves run with
    (``reduced_options`` over the full options): a looser reduced ``eps_abs`` cannot leave
    rows "violated" that the reduced solve may not satisfy any better."""
    ocp = _grouped_qp(0)
    gen = DirectCompiled(ocp, "piqp", {"row_generation": {
        "reduced_options": {"eps_abs": 1e-6, "eps_rel": 1e-7}}})
    rg = gen.rowgen
    tol = rg._tolerance(np.array([0.0, 10.0]), np.array([0.0, 0.0]))
    assert np.allclose(tol, [1e-6, 1e-6 + 1e-7 * 10.0])
    sol = gen.solve({"c": np.full(6, 4.0)})
    assert sol.status == Status.OPTIMAL


def test_split_matches_the_program_blocks():
    """The equality and inequality blocks row generation works on (from the engine's
    ``_row_blocks``) are the rows of the program's ``A`` with the values passed."""
    ocp = _grouped_qp(2)
    rg = DirectCompiled(ocp, "piqp", ROWGEN).rowgen
    A = rg.prog.A
    values = np.arange(1.0, A.nnz + 1.0)
    A_eq, G = rg._split(values)
    coded = A.copy()
    coded.data = values
    dense = coded.toarray()
    assert np.array_equal(A_eq.toarray(), dense[:rg.m0])
    assert np.array_equal(G.toarray(), dense[rg.m0:])


def _msd3_controller(**kw):
    from balustrade.control.rapsf import RAPSF
    from balustrade.estimate import BoxUpdate
    from balustrade.reproduce import msd_adaptive

    d = msd_adaptive.design(3)
    s = d["setup"]
    kw.setdefault("target", msd_adaptive.TARGET)
    return d, RAPSF(d["system"], d["X0"], msd_adaptive.joint(d), None, s.W, d["K"], s.N,
                    s.Theta0, estimator=BoxUpdate(d["system"], s.W, s.Theta0), **kw)


def test_rapsf_row_generation_only_for_the_preset_itself(monkeypatch):
    """A user's Target named like a preset of ROWGEN_FROM but with its own options is not
    swapped for ``fast-convex-rowgen``; the preset itself is; ``row_generation=False`` (a
    constructor argument) keeps the target; a non-bool is refused."""
    import balustrade.control.rapsf as rapsf_mod
    from balustrade.backends import resolve_target
    from balustrade.backends.targets import Target

    monkeypatch.setattr(rapsf_mod, "ROWGEN_MIN_ROWS", 1)
    own = Target("direct", "piqp", {"eps_abs": 1e-7}, name="fast-convex-qp")
    _, ctrl = _msd3_controller(target=own)
    ocp = ctrl._problem(ctrl.N, n_vertices=ctrl._n_compiled)
    assert ctrl._target_for(ocp) is ctrl.target
    assert dict(ctrl._target_for(ocp).options) == {"eps_abs": 1e-7}
    _, ctrl = _msd3_controller(target="fast-convex-qp")
    assert ctrl._target_for(ocp).name == "fast-convex-rowgen"
    _, ctrl = _msd3_controller(target=resolve_target("fast-convex-qp"), row_generation=False)
    assert ctrl._target_for(ocp).name == "fast-convex-qp"
    with pytest.raises(BalustradeError, match="row_generation"):
        _msd3_controller(target="fast-convex-qp", row_generation=1)


def test_rapsf_switching_row_generation_recompiles(monkeypatch):
    """Setting ``RAPSF.row_generation`` after steps drops the problems compiled for the other
    choice: the next step compiles (4.5) without row generation."""
    import balustrade.control.rapsf as rapsf_mod
    from balustrade.reproduce import msd_adaptive
    from benchmarks.bench_rapsf import Loop

    assert msd_adaptive.TARGET in rapsf_mod.ROWGEN_FROM
    monkeypatch.setattr(rapsf_mod, "ROWGEN_MIN_ROWS", 1)
    d, ctrl = _msd3_controller()
    loop = Loop(d, ctrl.step, 3)
    loop(0)
    assert any(getattr(c, "rowgen", None) is not None for c in ctrl._compiled.values())
    ctrl.row_generation = False
    loop(1)
    assert ctrl._compiled
    assert all(getattr(c, "rowgen", None) is None for c in ctrl._compiled.values())


def _scaled_grouped_qp(seed: int = 0) -> OCP:
    """:func:`_grouped_qp` whose grouped rows read ``(1 + k_g) a_rᵀ y <= 1 + g_r + d_g`` with
    parameters ``k`` and ``d`` per group: their coefficients (the values of ``A(p)``) and
    their bounds change with ``p``."""
    rng = np.random.default_rng(seed)
    ocp = OCP(name=f"scaled{seed}")
    y = ocp.variable("y", 6)
    c = ocp.parameter("c", 6)
    k = ocp.parameter("k", 8)
    d = ocp.parameter("d", 8)
    marks = {}
    for g in range(8):
        a = rng.normal(size=(12, 6))
        h = 1.0 + rng.uniform(0.0, 0.5, 12)
        ocp.le((1.0 + k[g]) * ca.mtimes(ca.DM(a), y), ca.DM(h) + d[g], name=f"group_{g}")
        marks[f"group_{g}"] = np.full(12, g)
    ocp.le(y, 3.0, name="upper")
    ocp.le(-y, 3.0, name="lower")
    ocp.minimize(squared_norm(y - c))
    ocp.row_groups = marks
    return ocp


@pytest.mark.parametrize("make", [_grouped_qp, _scaled_grouped_qp])
def test_reused_solver_gives_the_full_solve_answer(make):
    """Rounds whose rows are those of the last reduced solve update that PIQP solver
    (``reuse_solver``, session 13) with the new ``q``, ``h`` and values of ``A(p)``: the
    answers stay the full solve's. (A solver whose data were not updated would answer the
    last QP; a result array left as a view of the solver's memory would change under a
    later solve: both are checked.)"""
    ocp = make(0)
    full, gen = DirectCompiled(ocp, "piqp"), DirectCompiled(ocp, "piqp", ROWGEN)
    assert gen.rowgen.reuse_solver
    rng = np.random.default_rng(7)
    reused, kept = 0, []
    for _ in range(8):
        params = {"c": rng.normal(scale=4.0, size=6)}
        if "k" in ocp.parameters:
            params["k"] = rng.uniform(-0.3, 0.3, size=8)
            params["d"] = rng.uniform(0.0, 0.5, size=8)
        a, b = full.solve(params), gen.solve(params)
        assert a.status == b.status == Status.OPTIMAL
        assert np.max(np.abs(a.primal["y"] - b.primal["y"])) < 1e-7
        assert abs(a.objective - b.objective) < 1e-7
        reused += gen.rowgen.stats.reused
        p = ocp.pack_parameters(params)
        prog = gen.program
        raw = gen.rowgen.run(prog.q(p), prog.b(p), prog.A_data(p))
        kept.append((raw.y, raw.y.copy()))
    assert reused >= 4                           # the update path was taken
    for y, copy in kept:                        # not overwritten by later solves
        assert np.array_equal(y, copy)


def test_reuse_solver_off_sets_up_every_round():
    ocp = _grouped_qp(1)
    gen = DirectCompiled(ocp, "piqp", {"row_generation": {"reuse_solver": False}})
    for c in (np.full(6, 4.0), np.full(6, -4.0), np.full(6, 4.0)):
        assert gen.solve({"c": c}).status == Status.OPTIMAL
        assert gen.rowgen.stats.reused == 0
    with pytest.raises(BalustradeError, match="reuse_solver"):
        DirectCompiled(ocp, "piqp", {"row_generation": {"reuse_solver": 1}})


@pytest.mark.slow
def test_rapsf_eight_masses_default_loop_equals_full_solve():
    """The 8-mass default (RAPSF's size rule: row generation of (4.5) on PIQP, session 15's
    settings: one row per violated group and round, reduced solves without equilibration)
    along a closed loop of Algorithm 4.1: at every step the same (4.5) solved whole (every
    one of its 28644 tube rows, no row generation) gives the row generation's ``v_0`` within
    1e-6 and its objective within 1e-7 (relative), as does session 14's row generation (3
    rows per group and round, equilibrated reduced solves), and some step needs a second
    round (so the all-row check decides). An independent computation of what issue #15's
    8-mass step applies."""
    import copy

    from balustrade.reproduce import msd_adaptive
    from benchmarks.bench_rapsf import Loop

    d = msd_adaptive.design(8)
    ctrl = msd_adaptive.adaptive_controller(d)
    loop = Loop(d, ctrl.step, 8)
    loop(0)                                                    # compiles
    compiled = next(c for key, c in ctrl._compiled.items() if key[0] == ctrl.N)
    gen = compiled.rowgen
    assert gen is not None and gen.per_round == 1 and gen.reduced["preconditioner_iter"] == 0
    full = copy.copy(compiled)
    full.rowgen = None
    old = copy.copy(compiled)
    old.rowgen = compiled._row_generation(
        {"per_round": 3, "reduced_options": {"kkt_solver": "sparse_ldlt_ineq_cond"}})
    seen = []
    solve = compiled.solve

    def both(params=None, warm_start=None):
        sol = solve(params, warm_start=warm_start)
        rounds = gen.stats.rounds
        seen.append((sol, full.solve(params), rounds))
        seen.append((old.solve(params), seen[-1][1], 0))
        return sol

    compiled.solve = both
    for k in range(1, 8):
        loop(k)
    assert len(seen) == 14 and loop.fallbacks == 0
    for sol, whole, _ in seen:
        assert sol.status == whole.status == Status.OPTIMAL
        assert np.max(np.abs(sol.primal["v"][:, 0] - whole.primal["v"][:, 0])) < 1e-6
        assert abs(sol.objective - whole.objective) <= 1e-7 * (1.0 + abs(whole.objective))
    assert max(r for _, _, r in seen) > 1
