"""Remark 4.6 (SPEC §2.21): after an optimal shrunk-horizon solve the stored plan is the
shrunk plan (audit session 13, finding 1).

The scenario of the audit (``a9_shrunk.py``): the 3-mass chain of SPEC §3.2, ``θ*`` at a
vertex of ``Θ₀``, vertex disturbances; (4.5) is made to fail at steps ``k0`` and ``k0 + 1``
and the shrunk solve at ``k0 + 1``. At ``k0`` the shrunk solve succeeds and the state moves
along *its* tube; at ``k0 + 1`` the stored-plan fallback ``K x + plan[:, k_inf]`` must belong
to that tube, i.e. ``x_{k0+1}`` lies in the stored set ``z_{k_inf} ⊕ α_{k_inf} 𝕏₀``. With
the plan of the last full solve (the old code) the state lay outside it by 0.25–0.86 (tube
boundary = 1)."""

from __future__ import annotations

import numpy as np
import pytest

from balustrade.backends.solution import Solution
from balustrade.control.rapsf import RAPSF
from balustrade.estimate import BoxUpdate
from balustrade.models.msd import msd_performance
from balustrade.problems.rapsf import model_matrices
from balustrade.reproduce import msd_adaptive as M

TOL = 1e-6


@pytest.fixture(scope="module")
def msd3() -> dict:
    return M.design(3)


def _forced(c: RAPSF, k0: int) -> None:
    """(4.5) fails at ``k0`` and ``k0 + 1``, the shrunk solve at ``k0 + 1``."""
    real = c._solve

    def solve(x: np.ndarray, up: np.ndarray, horizon: int) -> Solution:
        if (horizon == c.N and c.k in (k0, k0 + 1)) or (horizon < c.N and c.k == k0 + 1):
            return Solution("failed", float("nan"), {}, {}, 0.0, 0, "test", "forced")
        return real(x, up, horizon)

    c._solve = solve


def _excess(HX: np.ndarray, tube: tuple[np.ndarray, np.ndarray], j: int, x: np.ndarray
            ) -> float:
    """``max_r [H_X]_r (x − z_j) − α_j`` (<= 0: ``x ∈ z_j ⊕ α_j 𝕏₀``)."""
    return float(np.max(HX @ (x - tube[0][:, j]) - tube[1][j]))


@pytest.mark.parametrize("seed, k0", [(0, 20), (2, 33)])
def test_fallback_after_shrunk_solve_stays_in_the_stored_tube(msd3: dict, seed: int,
                                                               k0: int) -> None:
    d = msd3
    s, sysm = d["setup"], d["system"]
    HX = d["X0"].H / d["X0"].h[:, None]
    c = RAPSF(sysm, d["X0"], M.joint(d), None, s.W, d["K"], s.N, s.Theta0,
              estimator=BoxUpdate(sysm, s.W, s.Theta0), target="fast-convex", shrinking=True)
    _forced(c, k0)
    rng = np.random.default_rng(seed)
    A, B = model_matrices(sysm, s.Theta0.vertices()[seed % 4])
    x = np.zeros(6)
    for k in range(k0 + 4):
        u, info = c.step(x, msd_performance(k, x, 3))
        if k == k0:
            assert info.fallback == "shrunk_horizon" and c.k_inf == 1
            short = info.solutions["rapsf_shrunk"]
            v_short = np.asarray(short["v"]).reshape(3, -1)
            # the stored plan from column k_inf on is the shrunk plan, and so is the tube
            assert np.array_equal(c.plan[:, 1:], v_short)
            assert np.allclose(c.tube[0][:, 1:], np.asarray(short["z"]).reshape(6, -1))
            assert np.allclose(u, d["K"] @ x + v_short[:, 0])
        if k == k0 + 1:
            assert info.fallback == "stored_plan" and c.k_inf == 2
            assert np.allclose(u, d["K"] @ x + v_short[:, 1])
            assert _excess(HX, c.tube, c.k_inf, x) <= TOL      # x in the stored tube
        assert np.max(np.abs(x)) <= 2.3 + TOL and np.max(np.abs(u)) <= 3.5 + TOL
        x = A @ x + B @ u + rng.choice([-1e-3, 1e-3], 6)


def test_full_solve_stores_its_tube(msd3: dict) -> None:
    """An optimal (4.5) stores ``(z, α)`` beside ``v``: ``x_k ∈ z_0 ⊕ α_0 𝕏₀`` (4.5b)."""
    d = msd3
    s = d["setup"]
    c = RAPSF(d["system"], d["X0"], M.joint(d), None, s.W, d["K"], s.N, s.Theta0,
              target="fast-convex")
    x = np.full(6, 0.3)
    u, info = c.step(x, np.zeros(3))
    assert info.fallback is None and c.tube is not None
    assert c.tube[0].shape == (6, s.N + 1) and c.tube[1].shape == (s.N + 1,)
    assert _excess(d["X0"].H / d["X0"].h[:, None], c.tube, 0, x) <= TOL


# -- the emitted C (codegen/c/rapsf.c) does the same ---------------------------------------------
N_TOY = 5


def test_c_stores_the_shrunk_plan_as_python(rapsf_toy, tmp_path) -> None:
    """C = Python on the 2-state toy (``tests/conftest.py``) for a stored-plan fallback right
    after an optimal shrunk solve: a full solve stores a plan; inflated ``s_jr`` make (4.5)
    infeasible while the horizon ``N − 1`` is not (``"shrunk_horizon"``); a state outside
    ``X`` then makes every horizon infeasible (``"stored_plan"``), whose input must be
    ``K x + v̂_1`` of the shrunk solve — in Python and in C."""
    from balustrade.codegen import CRAPSF, build, emit_rapsf
    from balustrade.codegen.emit_rapsf import EMITTABLE_TARGET, link_flags

    toy = rapsf_toy
    py = RAPSF(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N_TOY, toy.Theta0,
               target=EMITTABLE_TARGET, shrinking=True)
    em = emit_rapsf(py, "rsp", tmp_path)
    c = CRAPSF(build(tmp_path, em.name, werror=True, extra_flags=link_flags(em.libraries)),
               host=py)
    s_true = py._s.copy()
    x = np.array([0.05, 0.0])
    script = [(x, s_true, None), (x, np.full_like(s_true, 2.5), "shrunk_horizon"),
              (np.array([2.6, -2.4]), s_true, "stored_plan")]
    for k, (xk, sk, fallback) in enumerate(script):
        py._s = c.host._s = sk
        (u_py, i_py), (u_c, i_c) = py.step(xk, np.array([0.2])), c.step(xk, np.array([0.2]))
        assert i_py.fallback == i_c.fallback == fallback, (k, i_py, i_c)
        assert np.max(np.abs(u_py - u_c)) <= TOL, (k, u_py, u_c)
        if fallback == "shrunk_horizon":
            v_short = np.asarray(i_py.solutions["rapsf_shrunk"]["v"]).reshape(1, -1)
        if fallback == "stored_plan":
            assert c.k_inf == py.k_inf == 2
            assert np.allclose(u_c, toy.K @ xk + v_short[:, 1], atol=TOL)
