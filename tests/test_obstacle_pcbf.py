"""The PCBF algorithm on the nonconvex (2.24) of the obstacle car (Section 8.3): a local
optimum of (2.24) with a positive cost while the shifted plan has zero slack violated the
assumption behind the invariance of S_PB (docs/obstacles.md, "Why the exact PCBF entered
a disc"); the shifted-plan certificate (control/shifted.py) restores it."""

from __future__ import annotations

import numpy as np
import pytest

from balustrade.backends import Solution, compile
from balustrade.control.pcbf import PCBFSafetyFilter
from balustrade.control.shifted import ShiftedCertificate
from balustrade.models.obstacle_car import obstacle_car, obstacle_setup, signed_distance
from balustrade.problems.obstacles import stopping_filter_problem, stopping_pcbf_problem
from balustrade.testing import verify

N = 10  # 0.2 s: enough to stop from 0.8 m/s (0.16 s at τ = −5)
#: 0.08 m before the disc at (−0.8, −0.8), heading into it at 0.8 m/s
X0 = np.array([-1.03, -0.8, 0.0, 0.8, 0.0])
FULL_THROTTLE = np.array([2.0, 0.0])


@pytest.fixture(scope="module")
def car():
    system, s = obstacle_car(), obstacle_setup()
    deltas = s.delta_step * np.arange(N)
    args = (system, s.X, s.U, N, deltas, s.delta_step * N)
    return (system, s, compile(stopping_pcbf_problem(*args), "exact"),
            compile(stopping_filter_problem(*args), "exact"))


class LocalOptimum:
    """The compiled (2.24) whose solves, once ``spoil`` is set, report what a local solver
    returned on the car (measured: ``optimal`` with ``h_PB = 0.031`` where the shifted plan
    had zero slack): its own point with every slack raised to ``xi``."""

    def __init__(self, compiled, xi: float = 0.03):
        self.compiled, self.ocp, self.backend = compiled, compiled.ocp, compiled.backend
        self.xi, self.spoil = xi, False

    def solve(self, params, warm_start=None):
        sol = self.compiled.solve(params, warm_start=warm_start)
        if not self.spoil:
            return sol
        if self.spoil == "failed":
            nan = {k: np.full_like(np.asarray(v, float), np.nan) for k, v in sol.primal.items()}
            return Solution("failed", float("nan"), nan, {}, sol.solve_time, sol.iterations,
                            sol.backend, sol.solver, p=sol.p)
        primal = {**sol.primal, "xi": np.full_like(np.asarray(sol["xi"]), self.xi)}
        return Solution("optimal", float(self.xi * np.size(sol["xi"])), primal, sol.dual,
                        sol.solve_time, sol.iterations, sol.backend, sol.solver, p=sol.p)


def _two_steps(car, certificate: bool, spoil: bool | str = True, first: bool = False):
    """Two steps, the second on the spoilt (2.24); ``first``: ``certificate_first`` (the
    default; off here unless asked, so that (2.24) is solved and the certificate checked
    after it, the path these tests are about)."""
    system, s, slack, filt = car
    spoilt = LocalOptimum(slack)
    pcbf = PCBFSafetyFilter(spoilt, filt, s.U, shifted_certificate=certificate,
                            certificate_first=first and certificate)
    u0, info0 = pcbf.step(X0, FULL_THROTTLE)
    assert info0.status == "ok" and info0.values["h_PB"] <= 1e-9   # X0 is in S_PB
    x1 = system.step(X0, u0)
    spoilt.spoil = spoil
    u1, info1 = pcbf.step(x1, FULL_THROTTLE)
    return x1, u1, info1


def test_local_optimum_of_2_24_is_replaced_by_the_shifted_plan(car):
    """Fails without the certificate: the spurious ξ* = 0.03 (in squared metres, more than
    r² = 0.0225) would lift the disc rows of (2.23) (in closed loop the car then entered a
    disc, see the slow test below)."""
    x1, u1, info = _two_steps(car, certificate=True)
    assert info.values["shifted_certificate"] == 1.0
    assert info.values["h_PB_solver"] == pytest.approx(0.03 * N)
    assert info.values["h_PB"] == 0.0 and info.status == "ok" and info.fallback is None
    assert info.solutions["slack"].solver == "shifted_plan"  # the point the step used
    plan = np.asarray(info.solutions["filter"]["x"])
    assert signed_distance(plan.T).min() >= 0.0      # the (2.23) plan stays outside
    # the old behaviour: the local optimum is taken as h_PB and relaxes (2.23) by ξ* = 0.03
    _, _, old = _two_steps(car, certificate=False)
    assert old.values["h_PB"] == pytest.approx(0.03 * N)
    assert "shifted_certificate" not in old.values


def test_failed_2_24_with_a_certified_shift_runs_the_filter(car):
    """A failed (2.24) used to take fallback 2 (the shifted plan's next input, no (2.23));
    with a certified shift h_PB = 0 and (2.23) runs on zero slacks."""
    _, _, info = _two_steps(car, certificate=True, spoil="failed")
    assert info.values["shifted_certificate"] == 1.0 and np.isnan(info.values["h_PB_solver"])
    assert info.values["h_PB"] == 0.0 and info.fallback is None and info.status == "ok"
    _, _, old = _two_steps(car, certificate=False, spoil="failed")
    assert old.fallback == "shifted_plan"


def test_default_skips_the_spoilt_2_24_on_the_certificate(car):
    """With the default ``certificate_first`` the shifted plan is checked before (2.24):
    the local optimum (or failure) is never solved for, the step is ``"certified"`` with
    ``h_PB = 0`` and its (2.23) plan stays outside the discs. Fails if the default does not
    check the certificate first."""
    system, s, slack, filt = car
    assert PCBFSafetyFilter(slack, filt, s.U).certificate_first
    for spoil in (True, "failed"):
        _, _, info = _two_steps(car, certificate=True, spoil=spoil, first=True)
        assert info.values["certificate_first"] == 1.0 and info.values["h_PB"] == 0.0
        assert info.status == "certified" and info.fallback is None
        assert "shifted_certificate" not in info.values
        assert info.solutions["slack"].solver == "shifted_plan"
        plan = np.asarray(info.solutions["filter"]["x"])
        assert signed_distance(plan.T).min() >= 0.0


def test_certificate_is_exact_and_refuses_what_it_cannot_prove(car):
    system, s, slack, _ = car
    cert = ShiftedCertificate(slack, zero_tol=1e-9)
    brake = np.tile([[-5.0], [0.0]], (1, 8))            # stop within 8 steps, then zeros
    sol = cert.check(X0, brake)
    assert sol is not None and sol.status == "optimal" and sol.objective == 0.0
    assert verify(slack.ocp, sol, tol=1e-8).ok         # every block and bound, independently
    assert abs(np.asarray(sol["x"])[3, -1]) <= 1e-12 and not np.asarray(sol["xi"]).any()
    # full throttle into the disc: the zero-slack candidate violates a disc row
    assert cert.check(X0, np.tile(FULL_THROTTLE[:, None], (1, N))) is None
    # no stop within N steps (the tail inputs are 0): the hard terminal v_N = 0 fails
    assert cert.check(X0, np.zeros((2, 0))) is None
    assert cert.check(np.full(5, np.nan), brake) is None
    assert cert.check(X0, None) is None


def test_certificate_leaves_a_correct_positive_h_alone(car):
    """At a state outside S_PB the solver's h_PB > 0 is kept (no zero-slack plan exists)."""
    system, s, slack, filt = car
    pcbf = PCBFSafetyFilter(slack, filt, s.U)
    pcbf.step(X0, FULL_THROTTLE)
    unsafe = np.array([-0.9, -0.8, np.pi, 0.8, 0.0])  # inside the disc, leaving it
    _, info = pcbf.step(unsafe, FULL_THROTTLE)
    assert info.values["h_PB"] > 1e-3 and "shifted_certificate" not in info.values


@pytest.mark.slow
def test_exact_pcbf_with_the_default_warm_start_keeps_the_car_outside():
    """From (−2.0, 0.5) the default warm start (last (2.24) solution) entered a disc by
    0.12 m before the certificate (IPOPT: h_PB = 0.031 at step 33, shifted plan feasible with
    zero slack)."""
    from balustrade.reproduce import obstacles as R

    runs = R.closed_loops(R.pcbf_algorithm(shifted=False), R.NaiveMPC(),
                          starts=((-2.0, 0.5),), steps=45)
    assert runs[0]["min_distance"] >= -1e-3


@pytest.mark.slow
def test_exact_pcbf_keeps_every_reference_loop_outside():
    """HARD acceptance of §3.7 for the exact PCBF algorithm: the 5 starts, 70 steps, the
    library's default warm start (≈ 3 min; before the certificate: −0.139 m worst)."""
    from balustrade.reproduce import obstacles as R

    m = R.loop_metrics(R.closed_loops(R.pcbf_algorithm(shifted=False), R.NaiveMPC()))
    assert m["all_safe"] and m["min_signed_distance"] >= -1e-3


def test_exact_h_along_a_learned_run_finds_the_false_safe_state():
    """The reproduction's diagnosis of the learned loops: the exact h along a trajectory
    beside ĥ (here a surrogate that calls everything safe)."""
    from balustrade.reproduce import obstacles as R

    P = np.array([[-1.8, -1.0, 0.507, 3.0, 0.0],       # in S_PB (test_obstacles)
                  [-0.9, -0.8, np.pi, 0.8, 0.0]])      # inside a disc, leaving it
    run = {"start": [-1.8, -1.0], "states": P, "paths": ["certified"]}
    out = R.exact_h_along([run], lambda X: -np.ones(len(X)))["(-1.8, -1)"]
    assert out["first_step_h_positive"] == 1 and out["first_step_inside"] == 1
    assert out["h_there"] > 1e-3 and out["h_hat_there"] == -1.0
    assert out["path_before"] == "certified"
    assert out["steps_h_positive"] == 1 and out["steps_false_safe"] == 1
