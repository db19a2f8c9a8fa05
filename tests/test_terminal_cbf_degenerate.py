"""Issue 12: the terminal-CBF SDP (7.11)/(6.17) says when its level γ_f is degenerate, and
refuses bad input cleanly.

The linearized cart-pole (upright equilibrium, Euler, Ts = 0.05, box constraints) gives a
volume-maximal ellipsoid that touches the input bound: γ_f ≈ 1e-9, which used to be
returned as "optimal" without a word.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from balustrade.dsl.sets import Box
from balustrade.errors import (
    BalustradeError,
    BalustradeWarning,
    DegenerateResultWarning,
    NonFiniteError,
)
from balustrade.models.pendulum import pendulum, pendulum_setup
from balustrade.problems.terminal_cbf import DEGENERATE_LEVEL, synthesize_terminal_cbf


def cartpole(u_max: float = 5.0) -> tuple[np.ndarray, np.ndarray, Box, Box]:
    """Cart-pole (cart 1 kg, pole point mass 0.1 kg at 0.5 m) linearized upright, state
    (p, v, θ, ω), Euler with Ts = 0.05; |p|, |v|, |ω| <= 2, |θ| <= 0.5, |u| <= u_max."""
    M, m, l, g, Ts = 1.0, 0.1, 0.5, 9.81, 0.05
    Ac = np.array([[0, 1, 0, 0], [0, 0, -m * g / M, 0], [0, 0, 0, 1],
                   [0, 0, (M + m) * g / (M * l), 0]])
    Bc = np.array([[0.0], [1 / M], [0.0], [-1 / (M * l)]])
    bx = np.array([2.0, 2.0, 0.5, 2.0])
    return (np.eye(4) + Ts * Ac, Ts * Bc, Box(-bx, bx, name="X"),
            Box([-u_max], [u_max], name="U"))


def test_cartpole_degenerate_level_warns_and_names_the_input_rows() -> None:
    A, B, X, U = cartpole()
    with pytest.warns(DegenerateResultWarning) as rec:
        cbf = synthesize_terminal_cbf(A, B, X, U)
    assert issubclass(DegenerateResultWarning, BalustradeWarning)
    assert abs(cbf.gamma_f) < DEGENERATE_LEVEL  # the case of the issue: ~1e-9, "optimal"
    msg = str(rec[0].message)
    assert "input rows 0 (u_0 <= 5) and 1 (-u_0 <= 5) of 'U'" in msg
    assert "min_level" in msg and cbf.degenerate == msg
    assert cbf.limiting_rows == (0, 1)
    # the named rows are the active ones: b_j² = a_jᵀ K E Kᵀ a_j at the solution
    for j in cbf.limiting_rows:
        a, b = U.H[j], U.h[j]
        assert a @ cbf.K @ cbf.E @ cbf.K.T @ a == pytest.approx(b ** 2, rel=1e-6)
    # ... and the reason is right: with a looser input bound the level is not degenerate
    with warnings.catch_warnings():
        warnings.simplefilter("error", DegenerateResultWarning)
        loose = synthesize_terminal_cbf(A, B, X, cartpole(10.0)[3])
    assert loose.gamma_f > 0.1 and loose.degenerate == ""


def test_min_level_reserves_a_level_on_which_the_policy_respects_U() -> None:
    A, B, X, U = cartpole()
    with warnings.catch_warnings():
        warnings.simplefilter("error", DegenerateResultWarning)
        cbf = synthesize_terminal_cbf(A, B, X, U, min_level=0.5)
    assert cbf.gamma_f >= 0.5 - 1e-6 and cbf.degenerate == ""
    # samples on the boundary of D_f = {h_f <= γ_f}: π_f(x) = Kx within U
    rng = np.random.default_rng(0)
    d = rng.normal(size=(2000, 4))
    L = np.linalg.cholesky(cbf.E)
    xs = (np.sqrt(1 + cbf.gamma_f) * (d / np.linalg.norm(d, axis=1, keepdims=True))) @ L.T
    assert np.allclose([cbf(x) for x in xs[:20]], cbf.gamma_f)
    assert np.max(np.abs(xs @ cbf.K.T)) <= 5.0 + 1e-6


def test_pendulum_level_is_not_degenerate() -> None:
    system, s = pendulum(), pendulum_setup()
    with warnings.catch_warnings():
        warnings.simplefilter("error", DegenerateResultWarning)
        cbf = synthesize_terminal_cbf(system.A, system.B, s.X, s.U, delta_N=s.deltas[-1])
    assert cbf.gamma_f > 1.0 and cbf.degenerate == ""


@pytest.mark.parametrize("kwargs, error, match", [
    ({"delta_N": np.nan}, NonFiniteError, r"delta_N \(Δ_\{N−1\}\): must be finite, got nan"),
    ({"delta_N": -np.inf}, NonFiniteError, "must be finite, got -inf"),
    ({"decrease_factor": np.nan}, NonFiniteError, "decrease factor λ: must be finite, got nan"),
    ({"delta_N": [0.1, 0.2]}, BalustradeError, "delta_N .*expected a real number, got list"),
    ({"min_level": -1.0}, BalustradeError, r"min_level: must lie in \[0, inf\)"),
    ({"min_level": np.inf}, NonFiniteError, "min_level: must be finite, got inf"),
    ({"X": None}, BalustradeError, "X: expected a Polytope, got NoneType"),
    ({"U": [-3, 3]}, BalustradeError, "U: expected a Polytope, got list"),
    ({"A": np.full((2, 2), np.nan)}, NonFiniteError, "A: contains NaN"),
])
def test_bad_input_is_refused_before_the_solver(kwargs: dict, error: type,
                                                match: str) -> None:
    system, s = pendulum(), pendulum_setup()
    args = {"A": system.A, "B": system.B, "X": s.X, "U": s.U, **kwargs}
    with pytest.raises(error, match=match):
        synthesize_terminal_cbf(**args)


def test_ch5_robust_design_is_input_limited_and_its_note_says_so() -> None:
    """§5.6: the terminal CBF of the ch5-robust reproduction (SDP (6.17) on X ⊖ E, U ⊖ κ(E))
    has γ_f ≈ 0 by the thesis' design; the reproduction prints a note instead of warning."""
    from balustrade.models.unstable2d import unstable2d, unstable2d_setup
    from balustrade.problems.rpi import ellipsoidal_rpi
    from balustrade.reproduce.ch5_robust import terminal_note

    system, s = unstable2d(), unstable2d_setup(30)
    error = ellipsoidal_rpi(system.A, system.B, s.W, s.X, s.U)
    X_E, U_E = error.tighten_state(s.X), error.tighten_input(s.U)
    with pytest.warns(DegenerateResultWarning, match=r"input rows 0 \(u_0 <= 1.3\d*\) and 1"):
        cbf = synthesize_terminal_cbf(system.A, system.B, X_E, U_E, delta_N=s.deltas()[-1])
    note = terminal_note(cbf)
    assert "input-limited" in note and "input row(s) 0, 1" in note
    assert terminal_note(synthesize_terminal_cbf(
        system.A, system.B, X_E, U_E, delta_N=s.deltas()[-1], min_level=1.0)).startswith(
        "note: terminal CBF level gamma_f = 1")


def test_the_sdp_is_a_synthesis_problem_with_named_blocks_and_a_target() -> None:
    """(7.11) is written in the synthesis language: one LMI block per thesis row, solved
    through a target (issue #13 §4)."""
    from balustrade.dsl.synthesis import SynthesisProblem
    from balustrade.errors import SolverError
    from balustrade.problems.terminal_cbf import terminal_cbf_sdp

    system, s = pendulum(), pendulum_setup()
    sdp = terminal_cbf_sdp(system.A, system.B, s.X, s.U, delta_N=s.deltas[-1])
    assert isinstance(sdp, SynthesisProblem) and sdp.sense == "minimize"
    assert list(sdp.constraints) == (["invariance"]
                                     + [f"state row {i}" for i in range(len(s.X.h))]
                                     + [f"input row {j}" for j in range(len(s.U.h))])
    with pytest.raises(SolverError, match="lower to cvxpy"):
        synthesize_terminal_cbf(system.A, system.B, s.X, s.U, target="exact-ipopt")
