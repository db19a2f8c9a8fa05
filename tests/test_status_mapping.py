"""Solver return codes → :class:`~balustrade.backends.Status`, the same in Python and in
the emitted C (issue #14, "no wrong answers").

fatrop's acceptable stop (``StopAtAcceptablePoint``: its acceptable tolerance held for
``acceptable_iter`` iterations, the requested one not met). The emitted C cannot tell it
from a failure (its fatrop returns nonzero unless fatrop ended with ``Success``,
``backends.emittable.STATUS_OPTIONS``), so it retries it and, when no retry converges,
reports the primal-feasible point as ``BAL_FEASIBLE``. The backend reads the same return
the same way: not a success, retried, then ``feasible`` when the point is primal feasible
(the PCBF step then takes its cost only as an upper bound on ``h_PB``), never
``optimal_inaccurate`` (which the step would use as ``h_PB``). The test target forces the
stop: ``tolerance`` 1e-16 (never met), ``tol_acceptable`` 1e-6 with ``acceptable_iter`` 1.
"""

from __future__ import annotations

import numpy as np
import pytest

from balustrade.backends import compile
from balustrade.backends.targets import Target
from balustrade.control import PCBFSafetyFilter
from balustrade.examples.pendulum import pendulum_terminal_cbf
from balustrade.models.pendulum import pendulum, pendulum_setup
from balustrade.problems.pcbf import pcbf_filter_problem, pcbf_slack_problem

#: fatrop stopping at its acceptable level (fatrop 1.1.8 option names), no retry: the
#: acceptable stop is the final answer of each solve, in Python and in C
ACCEPTABLE = Target("casadi", "fatrop",
                    {"fatrop": {"print_level": 0, "max_iter": 300, "tolerance": 1e-16,
                                "tol_acceptable": 1e-6, "acceptable_iter": 1}},
                    retries=(), name="fatrop-acceptable")
STATES = ([0.5, -0.3], [0.0, 0.0], [-0.8, 0.6], [0.3, 0.2], [-0.2, -0.4])


def _filter(target: Target = ACCEPTABLE) -> PCBFSafetyFilter:
    system, s = pendulum(), pendulum_setup()
    args = (system, s.X, s.U, pendulum_terminal_cbf(), s.N, s.deltas)
    slack = compile(pcbf_slack_problem(*args, alpha_f=s.alpha_f, slack_norm=1), target)
    return PCBFSafetyFilter(slack, compile(pcbf_filter_problem(*args), target), s.U)


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    from balustrade.codegen import accelerate

    py = _filter()
    c = accelerate(py, build_dir=tmp_path_factory.mktemp("acceptable"), name="accpcbf",
                   werror=True)
    return py, c


def test_fatrop_acceptable_stop_is_not_a_success():
    """The forced stop happens (message), and it is reported ``feasible`` (primal feasible,
    no convergence), never as a success: not ``optimal``, not ``optimal_inaccurate``."""
    slack = _filter().slack
    stops = 0
    for x in STATES:
        sol = slack.solve({"x0": x})
        if "StopAtAcceptablePoint" not in sol.message:
            continue
        stops += 1
        assert not sol.success, (x, sol.status)
        assert sol.status == ("feasible" if slack._primal_feasible(sol.raw["x"], sol.p)
                              else "failed"), (x, sol.status, sol.message)
    assert stops >= 3


def test_fatrop_acceptable_stop_c_equals_python(pair):
    """One step per state from a reset: the C step and the Python step agree on the
    statuses, fallbacks, uncertified solves and ``h_PB``/``h_PB_upper`` at the forced
    acceptable stops."""
    py, c = pair
    stops = 0
    for x in STATES:
        py.reset()
        c.reset()
        (u_py, a), (u_c, b) = py.step(np.asarray(x), np.array([1.0])), \
            c.step(np.asarray(x), np.array([1.0]))
        stops += "StopAtAcceptablePoint" in a.solutions["slack"].message
        assert (a.status, a.fallback, a.uncertified) == (b.status, b.fallback,
                                                         b.uncertified), x
        for key in ("h_PB", "h_PB_upper"):
            if key in a.values or key in b.values:
                np.testing.assert_allclose(b.values.get(key, np.nan),
                                           a.values.get(key, np.nan), atol=1e-6,
                                           equal_nan=True)
        np.testing.assert_allclose(u_c, u_py, atol=1e-6)
    assert stops >= 3
