"""Algorithm 5.2 in C keeps the start of a (5.15) apart from its last converged (5.15), as
:class:`~balustrade.control.robust.RobustPCBFSafetyFilter` does (review, session 14).

After a (5.15) answered on a recovery step, the next (5.15) starts from the candidate (5.17)
(``_slack_recovered``); without a candidate, from the last converged (5.15)
(``_last_slack``). The C used to write the candidate start over its only copy of the last
converged point (``slack.x0``), so when that (5.15) failed and the candidate could not be
built again (``<name>_candidate_exact`` 0), the next (5.15) started from the stale candidate
start where Python starts from its last converged point.

Forced on the 2-D example of Section 5.6 (N = 10, ``robust-sqp`` with its whole chain, the
interior-point retry leading recovery steps): a stand-in makes the candidate's terminal
input "not computable" beyond ``h_f(z_N) = H_DROP`` (as for a system without the closed form,
:func:`~balustrade.control.tube_functions.terminal_input_expr`), in the emitted C and in
Python alike (Python then keeps no candidate, as the C); a state of order 1e5 makes every
attempt of (5.15) fail.
"""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from test_emit_robust import _design, _kind
from test_lane_recovery import OUTSIDE

from balustrade.codegen import accelerate
from balustrade.control import tube_functions as T

#: between h_f(z_N) of the (5.15) optimizer at OUTSIDE[0] (679.8) and of its candidate
#: (828.6): the first candidate is built, the one shifted again at the failed step is not
H_DROP = 750.0
#: a state where every attempt of (5.15) fails (IPOPT: Maximum_Iterations_Exceeded)
BAD = np.array([38767.8763473, 33882.35183883])


@pytest.fixture(scope="module")
def dropping(tmp_path_factory: pytest.TempPathFactory) -> tuple:
    real = T.terminal_input_expr

    def stand_in(system, h_f, pi_f, U_E, zN, fit=True):  # noqa: ANN001, ANN202
        u_f, exact = real(system, h_f, pi_f, U_E, zN, fit)
        return u_f, exact * (h_f(zN) < H_DROP)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(T, "terminal_input_expr", stand_in)
        py, _ = _design()
        c = accelerate(py, build_dir=tmp_path_factory.mktemp("robust_start"), name="rstart")
    # Python drops the candidate where the C does (no SLSQP terminal input)
    py._make_candidate = lambda z, v, xi: py._tube.candidate(z, v, xi)
    return py, c


def _python_start(py) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The start of Python's next (5.15) (robust.py's ``_solve_slack``)."""
    warm = py.candidate.as_dict() if py._slack_recovered and py.candidate is not None \
        else py._last_slack
    x, lam_x, lam_g = py.slack._initial_guess(warm)
    return tuple(np.asarray(ca.DM(a)).reshape(-1) for a in (x, lam_x, lam_g))


def test_c_starts_from_the_last_converged_slack_solve_without_a_candidate(
        dropping: tuple) -> None:
    py, c = dropping
    py.reset()
    c.reset()
    x1, u_p = OUTSIDE[0], np.array([1.0])
    steps = [x1, BAD, BAD, x1]
    for k, x in enumerate(steps):
        (u1, i1), (u2, i2) = py.step(x, u_p), c.step(x, u_p)
        assert np.array_equal(u1, u2), (k, u1, u2, i1.status, i2.status)
        assert (_kind(i1.status), i1.fallback) == (_kind(i2.status), i2.fallback), \
            (k, i1.status, i2.status)
        if k == 0:   # answered by the led interior-point retry, candidate kept
            assert i1.status == "ok" and py._slack_recovered and py.candidate is not None
        if k == 1:   # failed from the candidate; the candidate shifted again is dropped
            assert i1.fallback == "candidate" and py.candidate is None
            assert i2.values.get("candidate_exact") == 0.0
        if k in (1, 2):  # the next (5.15) starts from the last converged one, in both
            start, want = c.slack.warm_start(), _python_start(py)
            for key, w in zip(("x0", "lam_x0", "lam_g0"), want):
                assert np.array_equal(start[key], w), (k, key, np.max(np.abs(start[key] - w)))
        if k == 2:
            assert i1.fallback == "projected_proposal"
