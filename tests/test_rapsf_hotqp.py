"""The measurement of a hot-started active-set QP against PIQP on (4.5)
(``benchmarks/rapsf_hotqp.py``, docs/adaptive.md "Hot-started active set (session 12)"):
its statuses are honest, the CasADi qpOASES memory really hot-starts, and on the 3-mass
closed loop both solvers give the same inputs."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import scipy.sparse as sp

from benchmarks.rapsf_hotqp import (
    RET_MAX_NWSR_REACHED,
    SUCCESSFUL_RETURN,
    HotQpoases,
    compare,
    kkt_residual,
    status_of,
)


def _small_qp(seed: int = 0) -> SimpleNamespace:
    """A QP shaped like (4.5): semidefinite Hessian (rank 2 of 6), one equality row, a box
    ``|y| <= 1`` and random rows (``A y + s = b``, ``s ∈ {0} × R₊``)."""
    rng = np.random.default_rng(seed)
    n = 6
    P = sp.diags([2.0, 1.0, 0, 0, 0, 0]).tocsc()
    A = sp.vstack([sp.csc_matrix(rng.standard_normal((1, n))), sp.eye(n), -sp.eye(n),
                   sp.csc_matrix(rng.standard_normal((4, n)))]).tocsc()
    b = np.concatenate([[0.1], np.ones(2 * n), np.ones(4)])
    return SimpleNamespace(P=sp.triu(P).tocsc(), A=A, b0=b, q0=rng.standard_normal(n),
                           cones=[("zero", 1), ("nonneg", A.shape[0] - 1)], conic=False)


def test_status_of_calls_only_a_checked_success_optimal() -> None:
    assert status_of(SUCCESSFUL_RETURN, False, 1e-12) == "optimal"
    assert status_of(SUCCESSFUL_RETURN, False, 1e-3) != "optimal"
    assert status_of(RET_MAX_NWSR_REACHED, False, 0.0) == "max_iterations"
    assert status_of(-1, True, 0.0) == "infeasible (unconfirmed)"
    assert status_of(-1, False, 0.0) == "failed"


def test_hot_start_is_hot_and_its_answers_meet_kkt() -> None:
    prog = _small_qp()
    hot = HotQpoases(prog)
    first = hot.run(prog.q0, prog.b0, None)
    assert first["status"] == "optimal" and first["iterations"] > 0
    again = hot.run(prog.q0, prog.b0, None)          # same data: the working set is optimal
    assert again["status"] == "optimal" and again["iterations"] == 0
    np.testing.assert_allclose(again["y"], first["y"], atol=1e-12)
    # changed data and A values (as when Θ_k changes the tube rows' coefficients)
    A = prog.A.data * (1.0 + 1e-3 * np.arange(prog.A.nnz) / prog.A.nnz)
    moved = hot.run(prog.q0 + 0.05, prog.b0, A)
    assert moved["status"] == "optimal" and moved["kkt"] < 1e-10
    # the KKT check is not vacuous: a shifted point fails it
    A_mat = sp.csc_matrix((A, prog.A.indices, prog.A.indptr), shape=prog.A.shape)
    P_full = sp.csc_matrix(prog.P + prog.P.T - sp.diags(prog.P.diagonal()))
    assert kkt_residual(P_full, prog.q0 + 0.05, A_mat, prog.b0, 1,
                        moved["y"] + 1e-3, hot.res["lam_a"]) > 1e-5


def test_a_limit_stopped_solve_is_not_optimal() -> None:
    prog = _small_qp()
    capped = HotQpoases(prog, {"nWSR": 1})
    out = capped.run(prog.q0, prog.b0, None)
    assert out["status"] == "max_iterations"


@pytest.mark.slow
def test_three_mass_loop_same_inputs_as_piqp() -> None:
    r = compare(3, 6)
    assert len(r["rows"]) == 5          # step 0 compiles (4.5) inside the step: not wrapped
    for row in r["rows"]:
        assert row["piqp_status"] == "optimal" and row["qp_status"] == "optimal"
        assert row["dv0"] < 1e-8
    assert any(row["qp_iter"] < r["rows"][0]["qp_iter"] for row in r["rows"][1:])
