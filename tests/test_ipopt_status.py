"""IPOPT's acceptable stop reported alike by Python and its emitted C (session 13, issues #14
and #16: "C = Python" statuses).

CasADi's generated IPOPT returns 0 (converged) for ``Solved_To_Acceptable_Level`` as for
``Solve_Succeeded`` (``error_on_fail``), where the backend reports ``optimal_inaccurate``.
IPOPT's own return status stays in the generated memory struct; the emitters export an
accessor for it (``backends.emittable.status_accessors``) and ``bal/problem.c`` flags such a
``BAL_OK`` (``<P>_inaccurate``), which the runtime loaders name ``optimal_inaccurate``.
"""

from __future__ import annotations

import numpy as np
import pytest

from balustrade.backends import compile
from balustrade.backends.emittable import STATUS_OPTIONS, status_accessors
from balustrade.backends.targets import Target
from balustrade.codegen import CProblem, build, emit_problem
from balustrade.codegen import emit as E
from balustrade.codegen.runtime import py_status
from balustrade.examples.codegen import PENDULUM_X0, pendulum_pcbf_filter

#: IPOPT with a tolerance it cannot meet and one acceptable iterate enough: it stops at
#: its acceptable level (15 iterations on the pendulum's (2.24))
ACCEPTABLE = {"ipopt.tol": 1e-30, "ipopt.acceptable_tol": 1e-6, "ipopt.acceptable_iter": 1}


def _states() -> list[np.ndarray]:
    return [np.asarray(x, dtype=float).reshape(2, 1) for x in np.asarray(PENDULUM_X0)]


@pytest.fixture(scope="module")
def problems(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The pendulum's (2.24) on IPOPT alone, stopping at its acceptable level (the emitted C
    keeps the target's ``acceptable_iter`` here: STATUS_OPTIONS without the emitted stop
    rule) and converging (the ``exact`` target), each in Python and in C."""
    ocp = pendulum_pcbf_filter().slack.ocp
    acc = compile(ocp, Target("casadi", "ipopt", ACCEPTABLE, retries=(),
                              name="ipopt-acceptable"))
    exact = compile(ocp, Target("casadi", "ipopt", {}, retries=(), name="ipopt-once"))
    out, flags = {}, E._link_flags(("ipopt",))
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(E, "STATUS_OPTIONS", {**STATUS_OPTIONS,
                                         "ipopt": {"error_on_fail": True}})
        d = tmp_path_factory.mktemp("ipopt_acceptable")
        em = emit_problem(acc, "ipacc", d, allow_external=True)
        out["acceptable"] = (acc, CProblem(build(d, em.name, werror=True, extra_flags=flags)))
    d = tmp_path_factory.mktemp("ipopt_exact")
    em = emit_problem(exact, "ipok", d, allow_external=True)
    out["exact"] = (exact, CProblem(build(d, em.name, werror=True, extra_flags=flags)))
    return out


@pytest.mark.parametrize("kind", ["acceptable", "exact"])
def test_c_reports_ipopts_acceptable_stop_as_python_does(problems: dict, kind: str) -> None:
    """The same status word per state, Python and C: ``optimal_inaccurate`` at IPOPT's
    acceptable stop (the C said ``ok`` before), ``optimal`` / ``ok`` when it converged."""
    py, c = problems[kind]
    seen = set()
    for x0 in _states():
        sol = py.solve({"x0": x0})
        status, value, _, w = c.solve({"x0": x0}, warm=False)
        expect = {"acceptable": "optimal_inaccurate", "exact": "optimal"}[kind]
        assert sol.status == expect, (kind, x0.ravel(), sol.message)
        assert status == ("ok" if expect == "optimal" else expect), (kind, x0.ravel())
        assert c.view.py_status(0) == expect  # the StepInfo word of the step loaders
        assert abs(value - float(sol.objective)) <= 1e-6 * (1.0 + abs(value))
        seen.add(status)
    assert len(seen) == 1


def test_status_names_and_the_accessor_rule() -> None:
    """``py_status`` names a flagged ``BAL_OK`` as the backend does, and only a ``BAL_OK``;
    an IPOPT symbol whose generated memory is not found is refused, not guessed."""
    assert py_status(0) == "optimal" and py_status(0, True) == "optimal_inaccurate"
    assert py_status(4, True) == "feasible"
    with pytest.raises(ValueError, match="no IPOPT memory"):
        status_accessors("int s(const casadi_real** arg) { return 0; }", "",
                         {"s": "IpoptInterface"})
    c, h = status_accessors("unchanged", "h", {"s": "Sqpmethod"})
    assert (c, h) == ("unchanged", "h")


def test_step_loaders_record_an_acceptable_stop_as_the_controllers_do() -> None:
    """The StepInfo words of the step loaders for a flagged ``BAL_OK``, as robust.py,
    multiobjective.py and pcbf.py record an ``optimal_inaccurate`` solve (``note_solve``:
    used, flagged in ``uncertified``, never ``"ok"`` for Algorithm 5.2 and the PCBF)."""
    from balustrade.codegen import status as S
    from balustrade.codegen.runtime import _pcbf_info
    from balustrade.codegen.runtime_robust import multiobjective_info, robust_info

    ok = S.code_of(S.SOLVE, "ok")
    r_ok = S.code_of(S.ROBUST, "ok")
    assert robust_info(r_ok, ok, ok, 0.1, 0.2).status == "ok"
    info = robust_info(r_ok, ok, ok, 0.1, 0.2, s_inaccurate=True)
    assert info.status == "slack_optimal_inaccurate" and info.values["h_r"] == 0.1
    info = robust_info(r_ok, ok, ok, 0.1, 0.2, f_inaccurate=True)
    assert info.status == "filter_optimal_inaccurate"
    assert info.uncertified == {"filter": "optimal_inaccurate"}
    info = robust_info(r_ok, ok, ok, 0.1, 0.2, s_inaccurate=True, f_inaccurate=True)
    assert info.status == "slack_optimal_inaccurate_filter_optimal_inaccurate"
    # a flag on a solve that did not return BAL_OK is not read
    info = robust_info(S.code_of(S.ROBUST, "candidate"), S.code_of(S.SOLVE, "not_converged"),
                       S.code_of(S.SOLVE, "not_run"), 0.1, 0.2, s_inaccurate=True)
    assert info.status == "slack_not_converged" and not info.uncertified
    m_ok = S.code_of(S.MULTIOBJ, "ok")
    info = multiobjective_info(m_ok, ok, ok, np.zeros(4), p_inaccurate=True)
    assert info.status == "ok" and info.uncertified == {"problem": "optimal_inaccurate"}
    p_ok = S.code_of(S.PCBF, "ok")
    assert _pcbf_info(p_ok, ok, ok, 0.0, float("nan")).status == "ok"
    info = _pcbf_info(p_ok, ok, ok, 0.3, float("nan"), s_inaccurate=True)
    assert info.status == "slack_optimal_inaccurate_filter_optimal"
    assert info.values["h_PB"] == 0.3 and info.uncertified == {"slack": "optimal_inaccurate"}
