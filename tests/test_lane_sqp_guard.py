"""A solve that sqpmethod reports converged at a point violating its constraints is
``failed``, never ``optimal`` (session 10). Seen on the lane change (§8.2): with (6.15g) in
running-sum form, at step 71 of seed 2 (ρ = 0.95) the eigenvalue-reflecting SQP retry
returned ``Solve_Succeeded`` at a point violating the rows by 8e7, and Algorithm 6.4
applied it (the state left X, h̃ reached 4e14). The emitted C tests its own KKT residuals
and rejects such a point; the Python backend now checks primal feasibility too.

The solver is replaced by a stand-in that returns a chosen point with sqpmethod's success
status, so the test does not depend on reproducing that solve."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from balustrade.backends import compile
from balustrade.backends.solution import Status
from balustrade.dsl import OCP, Box, LinearSystem, squared_norm


class _Reports:
    """A stand-in for a built ``sqpmethod``: returns ``x`` (multipliers 0) and stats that
    say it converged."""

    def __init__(self, x: np.ndarray, n_g: int):
        self.x, self.n_g = x, n_g

    def __call__(self, **_: object) -> dict:
        return {"x": ca.DM(self.x), "lam_x": ca.DM.zeros(self.x.size),
                "lam_g": ca.DM.zeros(self.n_g)}

    def stats(self) -> dict:
        return {"return_status": "Solve_Succeeded", "success": True, "iter_count": 3}

    def class_name(self) -> str:
        return "Sqpmethod"

    def name(self) -> str:  # a CasADi Function's name (Solution.raw["function"])
        return "reports"


@pytest.fixture(scope="module")
def problem():
    system = LinearSystem(np.array([[1.0, 0.1], [0.0, 1.0]]), np.array([[0.0], [0.1]]))
    ocp = OCP(system, 5)
    x0 = ocp.parameter("x0", 2)
    ocp.initial_state(x0)
    ocp.dynamics()
    ocp.state_constraint(Box([-1.0, -1.0], [1.0, 1.0]))
    ocp.input_constraint(Box([-1.0], [1.0]))
    ocp.minimize(squared_norm(ca.vec(ocp.u)))
    return compile(ocp, "robust-sqp")


def test_sqp_success_at_an_infeasible_point_is_failed(problem):
    p = problem.ocp.pack_parameters({"x0": np.array([0.5, 0.0])})
    good = problem.solve({"x0": np.array([0.5, 0.0])})
    assert good.status == Status.OPTIMAL
    x_good = np.asarray(good.raw["x"])
    ok = problem._solve_with(_Reports(x_good, problem.lbg.size), p, (x_good, 0.0, 0.0))
    assert ok.status == Status.OPTIMAL           # a feasible point keeps its verdict
    bad = x_good + 10.0                          # off the dynamics and the boxes
    sol = problem._solve_with(_Reports(bad, problem.lbg.size), p, (bad, 0.0, 0.0))
    assert sol.status == Status.FAILED and not sol.success
    assert "violating its constraints" in sol.message
