"""Value-function properties of the PCBF family on the pendulum (SPEC §4 items 1, 2, 9)."""

from __future__ import annotations

import numpy as np
import pytest

from balustrade.backends import compile
from balustrade.dsl import OCP
from balustrade.problems.pcbf import combined_h

TOL = 1e-6


def hard_feasible(pend, x: np.ndarray) -> bool:
    """SPEC §4.1: the hard-constrained problem (2.24b–d) with c_x + Δ_i <= 0, h_f <= 0."""
    ocp = OCP(pend.system, pend.N, name="hard")
    ocp.initial_state(x)
    ocp.dynamics()
    ocp.input_constraint(pend.U)
    ocp.state_constraint(pend.X, tightening=pend.deltas)
    ocp.terminal_cbf(pend.h_f)
    ocp.minimize(0)
    return compile(ocp, "cvxpy").solve().status == "optimal"


def test_h_pb_zero_at_origin_and_positive_outside_X(pend):
    assert abs(pend.h_pb(np.zeros(2))) <= TOL
    rng = np.random.default_rng(0)
    outside = rng.uniform([-2, -8], [2, 8], size=(200, 2))
    outside = outside[~np.array([pend.X.contains(x) for x in outside])][:20]
    assert len(outside) == 20
    for x in outside:
        c = np.asarray(pend.X.H @ x - pend.X.h)
        lower = np.sum(np.maximum(c, 0.0))  # ‖max(0, c_x(x))‖₁ (SPEC §4.2, ℓ1 slack norm)
        assert pend.h_pb(x) >= lower - TOL > 0.0


def test_zero_set_equals_hard_feasibility(pend):
    rng = np.random.default_rng(1)
    for x in rng.uniform([-0.7, -2.5], [0.7, 2.5], size=(30, 2)):
        assert (pend.h_pb(x) <= TOL) == hard_feasible(pend, x), x


@pytest.mark.parametrize("direction", [(1.0, 0.0), (1.0, 1.0), (1.0, -1.0), (-0.5, -1.0)])
def test_h_pb_and_h_continuous_across_boundary(pend, direction):
    d = np.array(direction) / np.linalg.norm(direction)
    ts = np.linspace(0.0, 1.0, 101)  # crosses ∂S_PB, stays where h_PB is moderate
    h_pb = np.array([pend.h_pb(t * d) for t in ts])
    h_bar = np.array([pend.h_bar(t * d) for t in ts])
    inside = h_pb <= TOL
    assert inside[0] and not inside[-1], "the line must cross the boundary of S_PB"
    # continuity: steps of 0.01 in x give small jumps (no discontinuity at ∂S_PB)
    h = np.array([combined_h(a, b) for a, b in zip(h_pb, h_bar)])
    assert np.max(np.abs(np.diff(h_pb))) < 0.5
    assert np.max(np.abs(np.diff(h))) < 0.5
    k = int(np.argmax(~inside))  # first point outside S_PB
    assert abs(h[k] - h[k - 1]) <= 0.05
    assert abs(h_bar[k - 1]) <= 0.05 and h_bar[k - 1] <= TOL  # h̄ → 0 at ∂S_PB


def test_extended_value_properties(pend):
    rng = np.random.default_rng(2)
    for x in rng.uniform([-1.0, -3.0], [1.0, 3.0], size=(40, 2)):
        h_pb, h_bar = pend.h_pb(x), pend.h_bar(x)
        # h̄ <= 0 ⟺ h_PB = 0 (SPEC §4.9)
        assert (h_bar <= TOL) == (h_pb <= TOL), (x, h_pb, h_bar)
        # h̄ >= max_j c_x,j(x)
        assert h_bar >= np.max(pend.X.H @ x - pend.X.h) - TOL
        # max{0, h} = h_PB
        assert max(0.0, combined_h(h_pb, h_bar)) == pytest.approx(h_pb, abs=TOL)
    # strictly negative strictly inside S_PB
    assert pend.h_bar(np.zeros(2)) < -0.1


def test_h_pb_decreases_along_closed_loop_from_outside(pend):
    from balustrade.control import PCBFSafetyFilter, simulate

    ctl = PCBFSafetyFilter(pend.compiled["slack", "casadi"], pend.compiled["filter", "casadi"],
                           pend.U)
    for x0 in ([1.5, -3.0], [-1.0, 2.0], [0.8, 0.0]):
        ctl.reset()
        trace = simulate(pend.system, ctl, x0, 40, proposal=2.0)
        h = trace.values["h_PB"]
        assert h[0] > 0.1
        assert np.all(np.diff(h) <= 1e-6), h
        assert h[-1] <= TOL
        assert trace.n_fallbacks == 0
