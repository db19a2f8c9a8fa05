"""A retry identical to an attempt already run is skipped (issue #14, session 12), in Python
(``casadi_backend._same_start``) and in the emitted C (``bal/problem.c``).

The default ``structured-ip`` chain is fatrop → cold fatrop → IPOPT. After a failed *cold*
first attempt (no warm start), the cold fatrop retry is the same solver from the same start:
deterministic, so the same run again. The test target forces fatrop's acceptable stop
(``tolerance`` 1e-16, never met; ``tol_acceptable`` 1e-6, ``acceptable_iter`` 1), which is
not a success, so every solve goes down the chain. The reference chain has a fatrop retry
with the same options as a separate solver object (not skipped): the answers are the same,
one attempt more. A warm first attempt keeps its cold fatrop retry.
"""

from __future__ import annotations

import numpy as np
import pytest

from balustrade.backends import compile
from balustrade.backends.targets import PRESETS, Target
from balustrade.examples.pendulum import pendulum_terminal_cbf
from balustrade.models.pendulum import pendulum, pendulum_setup
from balustrade.problems.pcbf import pcbf_slack_problem

_FATROP = {"fatrop": {"print_level": 0, "max_iter": 300, "tolerance": 1e-16,
                      "tol_acceptable": 1e-6, "acceptable_iter": 1}}
#: the structured-ip chain (fatrop, cold fatrop, IPOPT) on a fatrop that stops acceptably
CHAIN = Target("casadi", "fatrop", _FATROP, retries=PRESETS["structured-ip"].retries,
               name="fatrop-acceptable-chain")
#: the same chain with the cold fatrop as its own solver object (same options): never skipped
REFERENCE = CHAIN.with_retries((("fatrop", _FATROP), ("ipopt", {})))
STATES = ([0.5, -0.3], [0.0, 0.0], [-0.8, 0.6], [0.3, 0.2], [-0.2, -0.4])


def _slack(target: Target):
    system, s = pendulum(), pendulum_setup()
    return compile(pcbf_slack_problem(system, s.X, s.U, pendulum_terminal_cbf(), s.N,
                                      s.deltas, alpha_f=s.alpha_f, slack_norm=1), target)


def _counted(compiled) -> list:
    """Record the solver of every attempt ``compiled`` runs (one list per solve: clear it)."""
    runs: list = []
    inner = compiled._solve_with

    def counting(solver, p, guess):
        runs.append(solver)
        return inner(solver, p, guess)

    compiled._solve_with = counting
    return runs


def test_preset_chain_is_fatrop_cold_fatrop_ipopt():
    assert [s for s, _ in PRESETS["structured-ip"].retries] == ["fatrop", "ipopt"]
    assert dict(PRESETS["structured-ip"].retries[0][1]) == {}


def test_cold_duplicate_retry_is_skipped_with_the_same_answers():
    a, b = _slack(CHAIN), _slack(REFERENCE)
    runs_a, runs_b = _counted(a), _counted(b)
    chained = 0
    for x in STATES:
        runs_a.clear()
        runs_b.clear()
        sa, sb = a.solve({"x0": x}), b.solve({"x0": x})
        assert sa.status == sb.status, (x, sa.status, sb.status)
        np.testing.assert_array_equal(sa.raw["x"], sb.raw["x"])
        assert sa.objective == sb.objective or (np.isnan(sa.objective)
                                                and np.isnan(sb.objective))
        if len(runs_b) > 1:  # the first attempt failed: the chain ran
            chained += 1
            assert len(runs_a) == len(runs_b) - 1, (x, len(runs_a), len(runs_b))
            assert a.solver not in runs_a[1:]  # the cold fatrop did not run again
        else:
            assert len(runs_a) == 1
    assert chained >= 3


def test_warm_first_attempt_keeps_its_cold_retry():
    a = _slack(CHAIN)
    runs = _counted(a)
    retried = 0
    for x in STATES:
        first = a.solve({"x0": x})
        runs.clear()
        a.solve({"x0": x}, warm_start={"u": first["u"] + 0.01})  # not the cold start
        if len(runs) > 1:  # the warm attempt failed: the cold fatrop runs next
            retried += 1
            assert runs[:2] == [a.solver, a.solver], runs
    assert retried >= 3


def _pendulum_pair(build_dir, name: str, **filter_options):
    """The pendulum PCBF step on the chain, in Python and as emitted C."""
    from balustrade.codegen import accelerate
    from balustrade.control import PCBFSafetyFilter
    from balustrade.problems.pcbf import pcbf_filter_problem

    system, s = pendulum(), pendulum_setup()
    args = (system, s.X, s.U, pendulum_terminal_cbf(), s.N, s.deltas)
    py = PCBFSafetyFilter(_slack(CHAIN), compile(pcbf_filter_problem(*args), CHAIN), s.U,
                          **filter_options)
    return py, accelerate(py, build_dir=build_dir, name=name, werror=True)


def _attempts_of(c):
    """The C's ``<P>_attempts`` of the filter's slack problem: solver runs of its last solve."""
    import ctypes

    return c._lib.fn(f"{c.slack.info['prefix']}_attempts", ctypes.c_int, [ctypes.c_void_p])


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """The pendulum PCBF step on the chain, in Python and as emitted C (fatrop's C links
    libfatrop; its chain is fatrop, cold fatrop, IPOPT as in Python)."""
    return _pendulum_pair(tmp_path_factory.mktemp("dedup"), "dedup")


def test_c_skips_the_same_retry_and_answers_as_python(pair):
    py, c = pair
    assert c.slack.info["retries"] == ["fatrop", "ipopt"]  # the whole chain is emitted
    attempts = _attempts_of(c)
    runs = _counted(py.slack)
    chained = 0
    for x in STATES:
        py.reset()
        c.reset()
        runs.clear()
        (u_py, a), (u_c, b) = py.step(np.asarray(x), np.array([1.0])), \
            c.step(np.asarray(x), np.array([1.0]))
        assert (a.status, a.fallback) == (b.status, b.fallback), x
        np.testing.assert_allclose(u_c, u_py, atol=1e-6)
        assert len(runs) >= 1  # the step solved (2.24) (no plan to certify after a reset)
        assert attempts(c.slack.work) == len(runs), (x, len(runs))
        chained += len(runs) > 1
    assert chained >= 3


def _timing(reps: int = 6) -> None:  # pragma: no cover - a report, not a test
    """Median solve time of the chain with and without the duplicate attempt, interleaved."""
    import time

    a, b = _slack(CHAIN), _slack(REFERENCE)
    times: dict[str, list[float]] = {"dedup": [], "duplicate": []}
    for rep in range(reps):
        for x in STATES:
            order = (("dedup", a), ("duplicate", b)) if rep % 2 == 0 else \
                (("duplicate", b), ("dedup", a))
            for key, compiled in order:
                t0 = time.perf_counter()
                compiled.solve({"x0": x})
                times[key].append(time.perf_counter() - t0)
    d, u = np.array(times["dedup"]), np.array(times["duplicate"])
    print(f"median solve: skipped {1e3 * np.median(d):.1f} ms, repeated {1e3 * np.median(u):.1f}"
          f" ms, median ratio {np.median(d / u):.3f}")


if __name__ == "__main__":  # pragma: no cover
    _timing()



def test_c_warm_first_attempt_keeps_its_cold_retry(tmp_path):
    """The C's counterpart of :func:`test_warm_first_attempt_keeps_its_cold_retry`: the
    second step of a PCBF filter (no certificate first, so (2.24) is solved) warm-starts
    (2.24) from the first step's point; after that warm attempt the cold fatrop retry runs in
    the C as in Python — same attempt counts, statuses and inputs (fails if the C's
    ``ran_before`` skipped the retry whatever the start: a review's mutation that the cold
    tests did not catch)."""
    py, c = _pendulum_pair(tmp_path, "dedupw", certificate_first=False)
    attempts = _attempts_of(c)
    runs = _counted(py.slack)
    retried = 0
    for x in STATES:
        py.reset()
        c.reset()
        py.step(np.asarray(x), np.array([1.0]))
        c.step(np.asarray(x), np.array([1.0]))
        x2 = np.asarray(x) + 0.02
        runs.clear()
        (u_py, a), (u_c, b) = py.step(x2, np.array([1.0])), c.step(x2, np.array([1.0]))
        assert (a.status, a.fallback) == (b.status, b.fallback), x
        np.testing.assert_allclose(u_c, u_py, atol=1e-6)
        assert attempts(c.slack.work) == len(runs), (x, attempts(c.slack.work), len(runs))
        if len(runs) > 1:  # the warm attempt did not converge: the cold fatrop ran next
            retried += 1
            assert runs[:2] == [py.slack.solver, py.slack.solver], runs
    assert retried >= 3
