"""The synthesis part of the language (issue #13 §4): matrix/PSD variables, parameters, LMI and
SOC blocks, linear and log-det objectives, lowered once to cvxpy and solved many times."""

from __future__ import annotations

import numpy as np
import pytest

import balustrade.backends.synthesis_cvxpy as lowering
from balustrade.backends import (
    PRESETS,
    SynthesisSolution,
    Target,
    compile_synthesis,
    solve_synthesis,
)
from balustrade.dsl.synthesis import (
    SynthesisProblem,
    bmat,
    diag,
    hstack,
    logdet,
    multiply,
    norm,
    sum_squares,
    total,
    trace,
    vstack,
)
from balustrade.errors import BalustradeError, ConvexityError, ShapeError, SolverError

A = np.array([[1.0, 0.1], [0.0, 1.0]])
B = np.array([[0.005], [0.1]])


def ellipsoid_sdp(lam: float | None = None) -> SynthesisProblem:
    """max log det E s.t. [[λE, (AE+BY)ᵀ], [AE+BY, E]] ⪰ 0, |x_i| <= 1, |u| <= 1 ((7.11))."""
    sdp = SynthesisProblem("ellipsoid")
    E = sdp.matrix("E", (2, 2), symmetric=True)
    Y = sdp.matrix("Y", (1, 2))
    lam_ = sdp.parameter("lambda", value=0.99 if lam is None else lam, nonneg=True)
    AEBY = A @ E + B @ Y
    sdp.lmi("invariance", bmat([[lam_ * E, AEBY.T], [AEBY, E]]))
    for i in range(2):
        a = np.eye(2)[i:i + 1]
        sdp.lmi(f"state {i}", bmat([[1.0, a @ E], [(a @ E).T, E]]))
    sdp.lmi("input", bmat([[1.0, Y], [Y.T, E]]))
    sdp.maximize(logdet(E))
    return sdp


def test_terminal_ellipsoid_solves_and_satisfies_its_lmis() -> None:
    sol = solve_synthesis(ellipsoid_sdp())
    assert isinstance(sol, SynthesisSolution) and sol.ok and sol.status == "optimal"
    assert sol.target is PRESETS["sdp"] and sol.solve_time > 0
    E, Y = sol["E"], sol["Y"]
    assert E.shape == (2, 2) and Y.shape == (1, 2)
    assert np.allclose(E, E.T) and np.min(np.linalg.eigvalsh(E)) > 0
    P, K = np.linalg.inv(E), Y @ np.linalg.inv(E)
    Acl = A + B @ K
    # invariance: A_Kᵀ P A_K ⪯ λ P (Schur complement of the LMI)
    assert np.max(np.linalg.eigvalsh(Acl.T @ P @ Acl - 0.99 * P)) < 1e-6
    assert np.max(np.diag(E)) <= 1 + 1e-6 and (K @ E @ K.T).item() <= 1 + 1e-6
    assert sol.objective == pytest.approx(np.log(np.linalg.det(E)), rel=1e-6)
    assert set(sol.duals) == {"invariance", "state 0", "state 1", "input"}


def test_compiled_once_solved_with_new_parameters_equals_a_rebuild() -> None:
    compiled = compile_synthesis(ellipsoid_sdp(), target="sdp")
    assert compiled.cvxpy_problem.is_dpp()
    for lam in (0.5, 0.9, 0.99):
        again = compiled.solve({"lambda": lam})
        fresh = solve_synthesis(ellipsoid_sdp(lam))
        assert again.ok and fresh.ok
        assert np.allclose(again["E"], fresh["E"], rtol=1e-7, atol=1e-10)
    # a smaller λ (faster decrease) can only shrink the ellipsoid
    assert compiled.solve({"lambda": 0.5}).objective < compiled.solve({"lambda": 0.99}).objective


def test_second_order_cone_least_squares_and_linear_constraints() -> None:
    rng = np.random.default_rng(0)
    M, b = rng.standard_normal((6, 3)), rng.standard_normal(6)
    sdp = SynthesisProblem("least squares")
    x, t = sdp.vector("x", 3), sdp.scalar("t")
    bb = sdp.parameter("b", (6,), value=b)
    sdp.soc("residual", M @ x - bb, t)
    sdp.minimize(t)
    compiled = compile_synthesis(sdp)
    for rhs in (b, 2 * b):
        sol = compiled.solve({"b": rhs})
        ref = np.linalg.lstsq(M, rhs, rcond=None)[0]
        assert sol.ok and np.allclose(sol["x"], ref, atol=1e-6)
        assert sol["t"] == pytest.approx(np.linalg.norm(M @ ref - rhs), rel=1e-6)
    # linear (in)equalities, indexing, total: x_0 = 1, x_1 + x_2 >= 2, min ‖x‖ -> (1, 1, 1)
    sdp2 = SynthesisProblem("min norm")
    x, t = sdp2.vector("x", 3), sdp2.scalar("t", nonneg=True)
    sdp2.subject_to("pin", x[0] == 1)
    sdp2.subject_to("sum", total(x[1:]) >= 2)
    sdp2.subject_to("cone", norm(x) <= t)
    sdp2.minimize(t)
    sol = solve_synthesis(sdp2, "cvxpy")
    assert sol.ok and np.allclose(sol["x"], [1, 1, 1], atol=1e-6)


def test_psd_variables_trace_blocks_and_lmi_directions() -> None:
    C = np.array([[2.0, 1.0], [1.0, 3.0]])
    sdp = SynthesisProblem("max trace")
    X = sdp.matrix("X", (2, 2), psd=True)
    sdp.lmi("below C", X << C)          # X ⪯ C
    sdp.maximize(trace(X))
    sol = solve_synthesis(sdp)
    assert sol.ok and np.allclose(sol["X"], C, atol=1e-6)
    # hstack/vstack build the same matrix as bmat
    sdp2 = SynthesisProblem("stack")
    S = sdp2.matrix("S", (2, 2), symmetric=True)
    sdp2.lmi("schur", vstack([hstack([S, np.eye(2)]), hstack([np.eye(2), C])]))
    sdp2.minimize(trace(S))
    sol2 = solve_synthesis(sdp2)
    assert sol2.ok and np.allclose(sol2["S"], np.linalg.inv(C), atol=1e-5)


def test_statuses_are_the_common_vocabulary_with_a_message() -> None:
    sdp = SynthesisProblem("infeasible")
    x = sdp.scalar("x")
    sdp.subject_to("up", x >= 1)
    sdp.subject_to("down", x <= 0)
    sol = solve_synthesis(sdp)
    assert sol.status == "infeasible" and not sol.ok and sol.values == {}
    with pytest.raises(BalustradeError, match="infeasible"):
        sol["x"]
    sdp = SynthesisProblem("unbounded")
    x = sdp.scalar("x")
    sdp.subject_to("up", x >= 1)
    sdp.maximize(x)
    assert solve_synthesis(sdp).status == "unbounded"


def test_a_cone_too_large_for_the_memory_is_a_status_not_a_crash(monkeypatch) -> None:
    monkeypatch.setattr(lowering, "_mem_available_bytes", lambda: 1000.0)
    sol = solve_synthesis(ellipsoid_sdp())
    assert sol.status == "failed" and sol.message.startswith("too large")
    assert sol.info["psd_cone_sizes"][0] == 4
    # another solver is not refused
    assert solve_synthesis(ellipsoid_sdp(), solver="scs").ok


def test_errors_name_the_thing_before_any_solver_runs() -> None:
    sdp = SynthesisProblem("bad")
    X = sdp.matrix("X", (2, 2))
    Y = sdp.matrix("Y", (2, 2))
    with pytest.raises(ConvexityError, match="two variable"):
        X @ Y
    with pytest.raises(ShapeError):
        X @ np.ones((3, 1))
    with pytest.raises(ConvexityError, match="cannot minimize"):
        sdp.minimize(logdet(X))
    with pytest.raises(ConvexityError, match="convex <= concave"):
        sdp.subject_to("wrong side", 1 <= norm(X[:, 0]))
    with pytest.raises(ShapeError, match="2-D"):
        bmat([[X[0, :], X], [X, X]])
    with pytest.raises(BalustradeError, match="already declared"):
        sdp.matrix("X", (1,))
    sdp.subject_to("ok", X[0, 0] >= 1)
    with pytest.raises(BalustradeError, match="already exists"):
        sdp.subject_to("ok", X[0, 0] >= 1)
    p = sdp.parameter("p", (2,))
    sdp.subject_to("param", X[:, 0] <= p)
    with pytest.raises(BalustradeError, match="'p' has no value"):
        solve_synthesis(sdp)
    with pytest.raises(ShapeError):
        solve_synthesis(sdp, params={"p": np.ones(3)})
    with pytest.raises(BalustradeError, match="unknown parameters"):
        solve_synthesis(sdp, params={"q": 1.0})
    with pytest.raises(SolverError, match="lower to cvxpy"):
        compile_synthesis(sdp, target="exact")
    with pytest.raises(SolverError, match="uninstalled"):
        compile_synthesis(sdp, target=Target("cvxpy", "nosuchsolver"))
    with pytest.raises(BalustradeError, match="truth value"):
        if X[0, 0] >= 1:
            pass


def test_row_cones_sparse_constants_diag_and_sum_squares() -> None:
    import scipy.sparse as sp

    rng = np.random.default_rng(1)
    X0 = rng.standard_normal((4, 3))
    sdp = SynthesisProblem("row cones")
    X, s = sdp.matrix("X", (4, 3)), sdp.vector("s", 4)
    sdp.soc("rows", X - X0, s, axis=1)            # ‖X[i, :] − X0[i, :]‖ <= s_i
    sdp.subject_to("pin", sp.csr_matrix(np.eye(4)[:1]) @ X == 0)
    sdp.minimize(total(s) + 0.0 * sum_squares(diag(multiply(np.ones(4), s))))
    sol = solve_synthesis(sdp)
    assert sol.ok and np.allclose(sol["X"][0], 0, atol=1e-7)
    assert np.allclose(sol["X"][1:], X0[1:], atol=1e-6)
    assert sol["s"][0] == pytest.approx(np.linalg.norm(X0[0]), rel=1e-6)
    # 1-D items of vstack are rows, as in numpy
    assert vstack([s, s]).shape == (2, 4) and hstack([s, s]).shape == (8,)
    # shapes of huge expressions are inferred without allocating them
    big = SynthesisProblem("big").matrix("Z", (100000, 100000))
    assert (big[:, :3].T @ np.ones((100000, 2))).shape == (3, 2)
    with pytest.raises(ShapeError, match="bounds t"):
        sdp.soc("bad", X, s[:3], axis=1)


def test_docs_example_lq_terminal_ellipsoid() -> None:
    """The example of docs/language.md "Synthesis problems (SDPs)", run as written: the
    solution certifies V(Ax + BKx) − V(x) <= −(xᵀQx + uᵀRu) with V = xᵀ(γE⁻¹)x,
    V(x0) <= γ and |Kx| <= u_max on the ellipsoid, for each x0 without rebuilding."""
    import pathlib
    import re

    text = pathlib.Path(__file__).parents[1].joinpath("docs", "language.md").read_text()
    section = text.split("## Synthesis problems (SDPs)")[1]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    scope: dict = {"print": lambda *a: None}
    exec(compile(code, "docs/language.md", "exec"), scope)
    compiled = scope["compiled"]
    A_, B_, Q, R, u_max = (scope[k] for k in ("A", "B", "Q", "R", "u_max"))
    gammas = []
    for x in ([1.0, 0.0], [0.5, -1.0]):
        x0 = np.reshape(x, (2, 1))
        sol = compiled.solve({"x0": x0})
        assert sol.status == "optimal"
        E, g = sol["E"], sol["gamma"].item()
        P, K = g * np.linalg.inv(E), sol["Y"] @ np.linalg.inv(E)
        Acl = A_ + B_ @ K
        gap = Acl.T @ P @ Acl - P + Q + K.T @ R @ K
        assert np.max(np.linalg.eigvalsh(0.5 * (gap + gap.T))) <= 1e-6 * g
        assert (x0.T @ P @ x0).item() <= g * (1 + 1e-6)
        assert np.sqrt((K @ E @ K.T).item()) <= u_max * (1 + 1e-6)
        gammas.append(g)
    assert gammas[0] != pytest.approx(gammas[1])   # the parameter reached the solver


def test_a_solution_is_checkable_without_the_solver() -> None:
    """Principle 3: violations() evaluates every block with numpy alone."""
    sdp = ellipsoid_sdp()
    sol = solve_synthesis(sdp)
    v = sdp.violations(sol.values)
    assert set(v) >= {"invariance", "state 0", "state 1", "input", "symmetry of E"}
    assert max(v.values()) <= 1e-7
    assert sdp.value(sdp.objective, sol.values) == pytest.approx(sol.objective, rel=1e-8)
    bigger = {**sol.values, "E": 1.1 * sol["E"]}          # leaves the constraint set
    assert sdp.violations(bigger)["state 0"] > 1e-3 or sdp.violations(bigger)["state 1"] > 1e-3
    # a faster decrease λ = 0.5 is violated by the λ = 0.99 solution
    assert sdp.violations(sol.values, {"lambda": 0.5})["invariance"] > 1e-3


def test_a_nonsymmetric_lmi_is_refused_naming_the_block() -> None:
    sdp = SynthesisProblem("typo")
    E = sdp.matrix("E", (2, 2), symmetric=True)
    Y = sdp.matrix("Y", (1, 2))
    with pytest.raises(BalustradeError, match=r"lmi 'typo block': the matrix is not symmetric"):
        sdp.lmi("typo block", bmat([[E, Y.T], [2 * Y, np.eye(1)]]))
    sdp.lmi("symmetrized", bmat([[E, Y.T], [2 * Y, np.eye(1)]]), symmetrize=True)
    sdp.subject_to("trace", trace(E) <= 1)
    sdp.maximize(logdet(E))
    sol = solve_synthesis(sdp)
    assert sol.ok and sdp.violations(sol.values)["symmetrized"] <= 1e-7


def test_long_sums_lower_without_recursion_limits() -> None:
    sdp = SynthesisProblem("long sum")
    x = sdp.vector("x", 3000, nonneg=True)
    sdp.subject_to("floor", x >= 1)
    sdp.minimize(sum(x[i] for i in range(3000)))
    sol = solve_synthesis(sdp)
    assert sol.ok and sol.objective == pytest.approx(3000.0, rel=1e-7)
    assert sdp.violations(sol.values)["floor"] <= 1e-7
