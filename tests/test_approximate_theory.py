"""Closed-loop guarantees of the approximate PCBF filters (SPEC §4 item 10, §2.28, §2.34).

* Theorem 7.5 (Algorithm 7.5 with ``ĥ = h_PB + e_h``, ``|e_h| <= ε_h``): along the loop,
  ``h_PB(x⁺) − h_PB(x) <= −ρ max_u (h_PB(x) − h_PB(f(x, u))) + 4 ε_h`` at every step.
  ``h_PB`` is the optimal value of (2.24), evaluated exactly (IPOPT on the compiled
  problem, agreeing with Clarabel to ~1e-7); ``max_u`` is one convex program
  (:func:`next_step_problem`). The filter's ``ĥ`` is a CasADi expression: a cubic
  B-spline through exact values of ``h_PB`` on a grid plus a smooth synthetic error
  ``ε·sin(·)cos(·)``. The proof of Theorem 7.5 uses Assumption 7.4 only at ``x``, ``x⁺``
  and ``f(x, u*)`` (``u*`` maximizing the true decrease); ``ε_h`` is the largest
  ``|ĥ − h_PB|`` measured at exactly these points over the loop, so the check is the
  theorem's inequality with its own constant, not a tuned tolerance. A negative control
  (the proposal applied unfiltered) violates the same inequality.
* Algorithm 8.7 (:class:`GridPCBFFilter`) in closed loop with the terminal CBF
  ``ĥ = h_f`` of (7.11) (``{h_f <= 0}`` lies in the tightened ``X``): the multiplicative
  decrease whenever a grid input meets it, the rate limits, the recorded fallbacks, and
  the state constraints from inside ``{ĥ <= 0}``.
"""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from balustrade.backends import compile
from balustrade.control.approximate import ApproximatePCBFFilter, GridPCBFFilter
from balustrade.control.base import simulate
from balustrade.design.terminal_cbf import synthesize_terminal_cbf
from balustrade.dsl import OCP, sum_norms
from balustrade.learn.sampler import ProblemSpec
from balustrade.models.pendulum import pendulum, pendulum_setup

SYS = pendulum()
SETUP = pendulum_setup()
A, B = np.asarray(SYS.A, float), np.asarray(SYS.B, float)[:, 0]
H_F = synthesize_terminal_cbf(SYS.A, SYS.B, SETUP.X, SETUP.U, delta_N=SETUP.deltas[-1])
CAP = 20.0  # the surrogate is clipped here; the loops stay where h_PB is far below


def next_step_problem() -> OCP:
    """``min_{u ∈ U} h_PB(f(x, u))`` as one convex program: (2.24) at ``x⁺ = f(x, u_0)``
    with ``u_0`` free, i.e. horizon ``N + 1``, the slacked state constraints on steps
    ``1..N`` with tightening ``Δ_0..Δ_{N−1}`` and the terminal CBF at step ``N + 1``
    (``h_PB`` is jointly convex in the initial state and the decision variables, so the
    partial minimum over ``u_0`` is exact). Parameters: ``x0``."""
    X, N = SETUP.X, SETUP.N
    ocp = OCP(SYS, N + 1, name="pcbf_next_step")
    ocp.initial_state(ocp.parameter("x0", SYS.nx))
    ocp.dynamics()
    ocp.input_constraint(SETUP.U)
    xi = ocp.state_constraint(X, steps=range(1, N + 1), tightening=SETUP.deltas,
                              slack=ocp.variable("xi", X.n_rows, N, lb=0.0, role="slack"))
    xi_N = ocp.terminal_cbf(H_F, slack=ocp.variable("xi_N", 1, 1, lb=0.0, role="slack"))
    ocp.minimize(SETUP.alpha_f * xi_N + sum_norms(xi, 1, label="slack"))
    return ocp


class ExactPCBF:
    """``h_PB`` (2.24) and ``min_u h_PB(f(x, u))``, exact optimal values (warm-started)."""

    def __init__(self) -> None:
        self.p = ProblemSpec.of("pendulum", target="exact").build()
        self.next_step = compile(next_step_problem(), "sampling-cold")
        self._warm = None
        self.n_solves = 0

    def __call__(self, x: np.ndarray) -> float:
        x = np.asarray(x, float).reshape(-1)
        self.n_solves += 1
        sol = (self.p.slack.solve({"x0": x}, warm_start=self._warm) if self._warm is not None
               else self.p.slack_cold.solve({"x0": x}))
        if not sol.success:
            sol = self.p.slack_cold.solve({"x0": x})
        assert sol.success, (x, sol.status)
        self._warm = sol
        return max(float(sol.objective), 0.0)

    def min_next(self, x: np.ndarray) -> tuple[float, float]:
        """``(u*, min_u h_PB(f(x, u)))``."""
        self.n_solves += 1
        sol = self.next_step.solve({"x0": np.asarray(x, float)})
        assert sol.success, (x, sol.status)
        return float(np.asarray(sol["u"])[0, 0]), max(float(sol.objective), 0.0)


@pytest.fixture(scope="module")
def exact() -> ExactPCBF:
    return ExactPCBF()


@pytest.fixture(scope="module")
def surrogate(exact) -> ca.Function:
    """A cubic B-spline through exact ``min(h_PB, CAP)`` on a grid over
    ``[−0.9, 0.9] × [−3.6, 3.6]`` (half of it computed: ``h_PB(−x) = h_PB(x)`` for the
    symmetric pendulum problem)."""
    psi = np.round(np.arange(0.0, 0.9 + 1e-9, 0.05), 10)
    omega = np.round(np.arange(-3.6, 3.6 + 1e-9, 0.15), 10)
    V = np.zeros((len(psi), len(omega)))
    for i, a in enumerate(psi):  # snake order: warm starts from the neighbour
        for j in (range(len(omega)) if i % 2 == 0 else reversed(range(len(omega)))):
            V[i, j] = min(exact(np.array([a, omega[j]])), CAP)
    psi_all = np.concatenate([-psi[:0:-1], psi])
    V_all = np.vstack([V[:0:-1, ::-1], V])
    return ca.interpolant("h_pb_spline", "bspline", [psi_all, omega], V_all.ravel(order="F"))


def test_next_step_problem_is_the_minimum_over_inputs(exact):
    """The one-program ``min_u h_PB(f(x, u))`` equals a brute-force scan over ``U``."""
    for x in (np.array([0.62, 0.3]), np.array([-0.4, 1.7]), np.array([0.1, -0.2])):
        u_star, m = exact.min_next(x)
        scan = [exact(A @ x + B * u) for u in np.linspace(-3, 3, 61)]
        assert m <= min(scan) + 1e-6
        assert exact(A @ x + B * u_star) == pytest.approx(m, abs=1e-6)
        assert m >= min(scan) - 0.05  # the scan's spacing (h_PB is Lipschitz in u)


def noisy(spline: ca.Function, eps: float):
    """``ĥ = spline + ε sin(9ψ + 2ω + 0.4) cos(4ω − 3ψ)``: smooth, ``|noise| <= ε``."""
    def h_hat(x):
        return spline(x) + eps * ca.sin(9 * x[0] + 2 * x[1] + 0.4) * ca.cos(4 * x[1] - 3 * x[0])
    return h_hat


def theorem_7_5_margins(exact, h_hat, states, rho):
    """Per step ``k``: ``(lhs, −ρ Δh_PB)`` and the errors ``|ĥ − h_PB|`` at ``x_k``,
    ``x_{k+1}`` and ``f(x_k, u*_k)`` (where the proof of Theorem 7.5 uses them)."""
    rows, errors = [], []
    for x, x_next in zip(states[:-1], states[1:]):
        h_x, h_next = exact(x), exact(x_next)
        u_star, h_min = exact.min_next(x)
        dh = h_x - h_min
        assert dh >= -1e-6  # h_PB is a CBF: some input never increases it
        rows.append((h_next - h_x, -rho * dh))
        for z, hz in ((x, h_x), (x_next, h_next), (A @ x + B * u_star, h_min)):
            errors.append(abs(float(h_hat(z)) - hz))
    return np.array(rows), max(errors)


CASES = [  # (ε of the synthetic error, ρ, x0, constant proposal u_p, branches taken)
    (0.02, 1.0, (0.62, 0.3), 3.0, {"ok"}),
    (0.05, 0.3, (0.62, 0.3), 3.0, {"ok"}),
    (0.02, 0.3, (-0.65, -0.2), -2.0, {"ok"}),
    (0.05, 1.0, (0.58, 1.2), 3.0, {"ok"}),
    # proposals that help: the certification shortcut and the exact shortcut fire too
    (0.02, 0.3, (-0.65, -0.2), 1.0, {"ok", "proposal_feasible", "certified"}),
    (0.05, 0.5, (0.6, -0.6), 0.0, {"ok", "proposal_feasible", "certified"}),
]


@pytest.mark.parametrize("eps, rho, x0, u_p, branches", CASES)
def test_theorem_7_5_iss_decrease_along_the_loop(exact, surrogate, eps, rho, x0, u_p,
                                                  branches):
    h_expr = noisy(surrogate, eps)
    x = ca.SX.sym("x", 2)
    h_hat = ca.Function("h_hat", [x], [h_expr(x)])
    ctl = ApproximatePCBFFilter(SYS, SETUP.U, h_hat, rho=rho, target="exact")
    steps = 12
    tr = simulate(SYS, ctl, np.array(x0), steps, proposal=u_p)
    assert not tr.stopped
    # at ρ = 1 the feasible set of (7.5) is the (7.6) minimizer itself; an IPOPT failure
    # there falls back to that minimizer, which satisfies (7.5) (Proposition 7.3)
    assert set(tr.fallbacks) <= {None, "max_decrease_solution"}
    rows, eps_h = theorem_7_5_margins(exact, h_hat, tr.states, rho)
    # Assumption 7.4 at the points the proof uses: the synthetic error plus the spline's
    assert eps_h <= eps + 0.03
    lhs, bound = rows[:, 0], rows[:, 1]
    assert np.all(lhs <= bound + 4 * eps_h + 1e-6), (lhs - bound).max()
    # the loop is not trivial: the filter acted (u ≠ u_p) and h_PB came down
    assert branches <= set(tr.statuses)
    assert np.any(np.abs(tr.inputs[:, 0] - u_p) > 0.5)
    h0 = exact(tr.states[0])
    assert h0 > 0.1 and exact(tr.states[-1]) < 0.5 * h0


def test_theorem_7_5_inequality_fails_without_the_filter(exact, surrogate):
    """Negative control: the proposal applied unfiltered breaks the same inequality."""
    eps, rho = 0.02, 0.3
    h_expr = noisy(surrogate, eps)
    x = ca.SX.sym("x", 2)
    h_hat = ca.Function("h_hat", [x], [h_expr(x)])
    x0 = np.array([0.62, 0.3])
    states = np.array([x0, SYS.step(x0, np.array([3.0]))])  # h_PB: 0.35 -> 3.0
    rows, eps_h = theorem_7_5_margins(exact, h_hat, states, rho)
    assert eps_h <= eps + 0.03
    assert rows[0, 0] > rows[0, 1] + 4 * eps_h + 1.0


# -- Algorithm 8.7 in closed loop ----------------------------------------------------------
RHO_GRID, HALF_WIDTH, SPACING = 0.9, 0.5, 0.1


def h_f_value(x: np.ndarray) -> float:
    x = np.asarray(x, float).reshape(-1)
    return float(x @ np.asarray(H_F.P) @ x - 1.0)


def replay_grid_filter(tr, g: GridPCBFFilter, u_init: float):
    """Recompute every step of Algorithm 8.7 from the trace, independently of the class:
    candidates ``clip(u_{k−1} + jΔu, U)``, ``|jΔu| <= ū``; returns per step whether a
    candidate met ``h_f(x⁺) <= ρ h_f(x)`` and whether the decrease was binding (the
    candidate closest to ``u_p`` violates it), and checks the applied input."""
    lb, ub = SETUP.U.lb[0], SETUP.U.ub[0]
    offsets = np.arange(-5, 6) * SPACING
    u_prev, feasible, binding = u_init, [], []
    for k in range(len(tr.inputs)):
        x, u, u_p = tr.states[k], tr.inputs[k, 0], tr.proposed[k, 0]
        cand = np.unique(np.round(np.clip(u_prev + offsets, lb, ub), 12))
        vals = np.array([h_f_value(SYS.step(x, [c])) for c in cand])
        ok = vals <= RHO_GRID * h_f_value(x)
        feasible.append(bool(ok.any()))
        binding.append(not ok[int(np.argmin(np.abs(cand - u_p)))])
        assert abs(u - u_prev) <= HALF_WIDTH + 1e-9 and lb <= u <= ub  # rate limit, U
        assert np.min(np.abs(cand - u)) <= 1e-9                        # u is a grid input
        if ok.any():
            assert tr.statuses[k] == "ok" and tr.fallbacks[k] is None
            assert h_f_value(tr.states[k + 1]) <= RHO_GRID * h_f_value(x) + 1e-12
            assert abs(u - u_p) == pytest.approx(np.min(np.abs(cand[ok] - u_p)), abs=1e-9)
        else:
            assert tr.statuses[k] == "no_decreasing_candidate"
            assert tr.fallbacks[k] == "grid_minimizer"
            assert h_f_value(tr.states[k + 1]) == pytest.approx(vals.min(), abs=1e-12)
        u_prev = u
    assert g.n_decrease_infeasible == tr.n_fallbacks == feasible.count(False)
    return np.array(feasible), np.array(binding)


@pytest.mark.parametrize("proposal", ["push", "destabilizing"])
def test_algorithm_8_7_keeps_the_safe_set_invariant(proposal):
    """From inside ``{ĥ <= 0}`` with a grid input meeting the decrease at every step, the
    state stays in ``{ĥ <= 0}`` ⊂ ``X`` while proposals push it out."""
    g = GridPCBFFilter(SYS, SETUP.U, H_F, half_width=HALF_WIDTH, spacing=SPACING,
                       rho=RHO_GRID)
    rng = np.random.default_rng(3)
    u_p = 2.0 if proposal == "push" else \
        (lambda k, x: np.clip(3 * np.tanh(4 * x[1]) + rng.normal(0, 0.5), -3, 3).reshape(1))
    tr = simulate(SYS, g, np.array([0.0, 0.5]), 100, proposal=u_p)
    feasible, binding = replay_grid_filter(tr, g, 0.0)
    assert feasible.all() and tr.n_fallbacks == 0
    h = np.array([h_f_value(x) for x in tr.states])
    assert np.all(h <= 0.0) and np.all(SETUP.X.contains_many(tr.states))
    # the decrease constrained the choice at many steps, near the boundary of {ĥ <= 0}
    assert binding.sum() >= 10 and h.max() > -0.2


def test_algorithm_8_7_records_fallbacks_and_recovers():
    """Outside ``{ĥ <= 0}`` with the rate limit binding, no grid input decreases ``ĥ`` at
    first: the grid minimizer is applied and recorded; then the decrease resumes, the state
    enters ``{ĥ <= 0}`` and stays in ``X``."""
    g = GridPCBFFilter(SYS, SETUP.U, H_F, half_width=HALF_WIDTH, spacing=SPACING,
                       rho=RHO_GRID)
    tr = simulate(SYS, g, np.array([0.5, 0.2]), 60, proposal=2.0)
    assert h_f_value(tr.states[0]) > 0
    feasible, _ = replay_grid_filter(tr, g, 0.0)
    assert tr.n_fallbacks >= 1 and not feasible[0]
    last_fallback = int(np.nonzero(~feasible)[0].max())
    h = np.array([h_f_value(x) for x in tr.states])
    inside = [k for k in range(last_fallback + 1, len(h)) if h[k] <= 0]
    assert inside, "the state never entered {ĥ <= 0} after the fallbacks"
    assert np.all(h[inside[0]:] <= 0) and np.all(SETUP.X.contains_many(tr.states[inside[0]:]))
