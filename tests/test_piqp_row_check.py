"""The direct backend's PIQP and Clarabel engines report an "optimal" whose point misses a
row in the row's own unit as ``optimal_inaccurate`` (backends/direct_engines.py ``ROW_TOL``,
``RowMiss``; audit E, session 15): rows scaled 1e6 and 1e-9 (1e-6) in one QP, where the
engine's answer (status solved) ignored the small rows; the reference is the cvxpy
transcription solved by Clarabel (its own scaling keeps them)."""

from __future__ import annotations

import numpy as np
import pytest

from balustrade.backends import compile
from balustrade.backends.direct_engines import ROW_TOL
from balustrade.backends.solution import Status
from balustrade.dsl import OCP, squared_norm


def _scaled_qp() -> OCP:
    """Three rows with parameter scales ``s``: ``s₀(y₀ + y₁) <= b₀``, ``s₁(y₁ − y₂) <= b₁``,
    ``s₂(y₀ + y₃) = b₂``, a box, and no quadratic cost on ``y₃``."""
    ocp = OCP(name="scaled_qp")
    y = ocp.variable("y", 4)
    c = ocp.parameter("c", 4)
    s = ocp.parameter("s", 3)
    bb = ocp.parameter("bb", 3)
    ocp.le(s[0] * (y[0] + y[1]), bb[0], name="r0")
    ocp.le(s[1] * (y[1] - y[2]), bb[1], name="r1")
    ocp.eq(s[2] * (y[0] + y[3]), bb[2], name="e0")
    ocp.le(y, 3.0, name="up")
    ocp.le(-y, 3.0, name="lo")
    ocp.minimize(squared_norm(y[:3] - c[:3]) + c[3] * y[3])
    return ocp


#: found by /work/briefs/s15/audit/e_daqp_scale.py (instance 114)
BADLY_SCALED = {"c": [2.0627765061867827, 0.2879356657335208, 1.382084404925907,
                      1.6693737016440027],
                "s": [1e6, 1e-9, 1e-9],
                "bb": [189227.7013213466, -7.889751584024787e-10, 1.8440458359997904e-10]}


#: instance 49 of the same script: the direct Clarabel said solved at objective −7.46
#: (cvxpy: −1.19) with the 1e-6-scaled rows ignored
SMALL_ROWS = {"c": [0.5454731352138555, 1.0276703830312668, 3.1633342050547046,
                    -2.640092388244698],
              "s": [1e6, 1e-6, 1e-6],
              "bb": [724551.0412860947, -4.587032086957834e-07, 3.4671926245029547e-07]}


def _miss(y: np.ndarray, p: dict) -> float:
    """The rows' misses in their own units (each row divided by its scale)."""
    s, bb = np.array(p["s"]), np.array(p["bb"])
    rows = np.array([y[0] + y[1], y[1] - y[2], y[0] + y[3]]) - bb / s
    return float(max(rows[0], rows[1], abs(rows[2]), 0.0))


@pytest.mark.parametrize("target, params", [("fast-convex-qp", BADLY_SCALED),
                                             ("fast-convex", BADLY_SCALED),
                                             ("fast-convex-conic", SMALL_ROWS)])
def test_optimal_keeps_badly_scaled_rows(target, params):
    """Clarabel (cvxpy) solves them (objectives 0.656 and −1.19); PIQP said solved at a point
    2.2 off the 1e-9-scaled equality (objective −2.67), the direct Clarabel at −7.46. An
    ``optimal`` from the direct backend must now be the reference's answer; a wrong point
    comes back ``optimal_inaccurate``."""
    ref = compile(_scaled_qp(), "conic").solve(params)
    assert ref.status == Status.OPTIMAL and _miss(ref.primal["y"].ravel(), params) < 1e-6
    sol = compile(_scaled_qp(), target).solve(params)
    if sol.status == Status.OPTIMAL:
        assert sol.objective == pytest.approx(ref.objective, rel=1e-6, abs=1e-6)
    else:
        assert sol.status == Status.OPTIMAL_INACCURATE and "own unit" in sol.message
        assert _miss(sol.primal["y"].ravel(), params) > ROW_TOL


@pytest.mark.parametrize("target", ["fast-convex-qp", "fast-convex-conic"])
def test_well_scaled_rows_stay_optimal(target):
    """The same QP with every scale 1: the answer optimal and equal to the reference's."""
    p = dict(BADLY_SCALED, s=[1.0, 1.0, 1.0], bb=[0.2, -0.8, 0.2])
    ref = compile(_scaled_qp(), "conic").solve(p)
    sol = compile(_scaled_qp(), target).solve(p)
    assert sol.status == Status.OPTIMAL and ref.status == Status.OPTIMAL
    assert sol.objective == pytest.approx(ref.objective, rel=1e-7, abs=1e-7)


def test_row_norms_by_reduceat_equal_scipy():
    """The PIQP engine's row norms (one reduceat over the values in row order) equal scipy's
    ``max |a_ij|`` per row on random sparse matrices with empty rows, explicit zeros and
    entries from 1e-9 to 1e9 (1 for a row without a nonzero)."""
    import scipy.sparse as sp

    from balustrade.backends.direct_engines import _row_order

    rng = np.random.default_rng(0)
    for _ in range(100):
        m, n = rng.integers(1, 30, size=2)
        M = sp.random(m, n, density=rng.uniform(0, 0.5), format="csc",
                      random_state=int(rng.integers(1 << 30)))
        M.data = rng.normal(size=M.nnz) * 10.0 ** rng.integers(-9, 9, M.nnz)
        if M.nnz:
            M.data[0] = 0.0
        perm, starts, rows, size = _row_order(M)
        norms = np.ones(size)
        if perm.size:
            norms[rows] = np.maximum.reduceat(np.abs(M.data[perm]), starts)
        ref = np.asarray(abs(M).max(axis=1).todense()).ravel()
        assert np.array_equal(np.where(norms > 0, norms, 1.0), np.where(ref > 0, ref, 1.0))
