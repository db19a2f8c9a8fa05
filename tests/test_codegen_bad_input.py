"""Issue 12, "no wrong answers": the emitted C and the code-generation API refuse bad input.

* a NaN or inf parameter used to come back from ``<problem>_solve`` as ``BAL_OK`` (NaN
  compares false, so the residual tests passed); now ``BAL_BAD_INPUT`` — checked from C
  (a driver compiled with -Werror, run under valgrind when available) and through ctypes
  without the Python checks;
* the C control steps fall back as the Python controllers do: a non-finite state → the
  projected proposal; non-finite proposal entries → read as 0, the filter runs as usual;
* the Python runtime raises ShapeError / NonFiniteError before calling C;
* the emitters refuse unwritable folders and wrong objects before CasADi runs.

One emitted PCBF library and one emitted problem are built per module.
"""

from __future__ import annotations

import re
import shutil
import subprocess

import numpy as np
import pytest

from balustrade.backends import compile
from balustrade.codegen import (
    CPCBFSafetyFilter,
    CProblem,
    build,
    build_executable,
    emit_approximate,
    emit_functions,
    emit_pcbf,
    emit_problem,
    load_manifest,
    write_example,
)
from balustrade.codegen import status as S
from balustrade.errors import BalustradeError, CodegenError, NonFiniteError, ShapeError
from balustrade.examples.codegen import emit_pendulum_pcbf, pendulum_pcbf_filter
from balustrade.models.pendulum import pendulum

DRIVER = r"""
/* Calls the emitted C with bad input directly, without any Python in between. */
#include <math.h>
#include <stdio.h>
#include "pendulum_pcbf.h"

int main(void) {
  pendulum_pcbf_work* wk = pendulum_pcbf_alloc();
  casadi_real p[pendulum_pcbf_slack_NP], x[pendulum_pcbf_NX] = {0.1, 0.2};
  casadi_real u_p[pendulum_pcbf_NU] = {2.0}, u[pendulum_pcbf_NU], h;
  int i, st;
  if (!wk) return 1;
  for (i = 0; i < pendulum_pcbf_slack_NP; ++i) p[i] = 0.1;
  p[0] = NAN;
  st = pendulum_pcbf_slack_solve(&wk->slack, p);
  printf("solve_nan %d %d %d\n", st, isnan(wk->slack.f), isnan(wk->slack.x[0]));
  p[0] = INFINITY;
  printf("solve_inf %d\n", pendulum_pcbf_slack_solve(&wk->slack, p));
  printf("solve_null %d\n", pendulum_pcbf_slack_solve(&wk->slack, 0));
  p[0] = 0.1;
  printf("solve_ok %d\n", pendulum_pcbf_slack_solve(&wk->slack, p));
  x[1] = NAN;
  pendulum_pcbf_step(x, u_p, u, &h, &st, wk);
  printf("step_nan_x %d %.17g %d %d\n", st, u[0], isnan(h),
         pendulum_pcbf_solve_status(wk, 0));
  x[1] = 0.2;
  u_p[0] = NAN;
  pendulum_pcbf_step(x, u_p, u, &h, &st, wk);
  printf("step_nan_u %d %.17g %d\n", st, u[0], pendulum_pcbf_proposal_replaced(wk));
  u_p[0] = -INFINITY;
  pendulum_pcbf_step(x, u_p, u, &h, &st, wk);
  printf("step_minf_u %d %.17g %d\n", st, u[0], pendulum_pcbf_proposal_replaced(wk));
  u_p[0] = 0.0;
  pendulum_pcbf_step(x, u_p, u, &h, &st, wk);
  printf("step_zero_u %d %.17g %d\n", st, u[0], pendulum_pcbf_proposal_replaced(wk));
  printf("step_null %d\n", pendulum_pcbf_step(0, u_p, u, &h, &st, wk));
  u_p[0] = 2.0;
  pendulum_pcbf_step(x, u_p, u, &h, &st, wk);
  printf("step_ok %d %d\n", st, isfinite(u[0]) && isfinite(h));
  pendulum_pcbf_free(wk);
  return 0;
}
"""


@pytest.fixture(scope="module")
def pcbf(tmp_path_factory: pytest.TempPathFactory) -> dict:
    out = tmp_path_factory.mktemp("pcbf_bad_input")
    emitted = emit_pendulum_pcbf(out)
    return {"out": out, "emitted": emitted, "lib": build(out, emitted.name, werror=True),
            "py": pendulum_pcbf_filter()}


@pytest.fixture(scope="module")
def problem(tmp_path_factory: pytest.TempPathFactory, pcbf: dict) -> dict:
    out = tmp_path_factory.mktemp("problem_bad_input")
    emitted = emit_problem(pcbf["py"].filter, "filt", out)
    return {"lib": build(out, emitted.name, werror=True), "emitted": emitted}


def _good_filter_params() -> dict:
    return {"x0": np.array([0.1, 0.2]), "u_p": np.array([2.0]),
            "xi": np.zeros((4, 10)), "xi_N": 0.0}


def test_c_driver_gets_bad_input_status_from_c(pcbf: dict) -> None:
    out = pcbf["out"]
    (out / "driver.c").write_text(DRIVER)
    exe = build_executable(out, main="driver.c", werror=True)
    cmd = [str(exe)]
    if shutil.which("valgrind"):
        cmd = ["valgrind", "--error-exitcode=9", "--leak-check=full", "-q", *cmd]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr
    res = {line.split()[0]: line.split()[1:] for line in proc.stdout.splitlines()}
    bad, ok = S.code_of(S.SOLVE, "bad_input"), S.code_of(S.SOLVE, "ok")
    step_bad = str(S.code_of(S.PCBF, "bad_input"))
    assert res["solve_nan"] == [str(bad), "1", "1"]  # refused, outputs NaN (was BAL_OK)
    assert res["solve_inf"] == [str(bad)] and res["solve_null"] == [str(bad)]
    assert res["solve_ok"] == [str(ok)]
    # NaN state: u_p = 2 clipped to U = [-3, 3], nothing solved (as PCBFSafetyFilter)
    assert res["step_nan_x"] == [step_bad, "2", "1", str(bad)]
    # a NaN or -inf proposal is read as 0 and filtered as usual: the input of u_p = 0
    ok_code = str(S.code_of(S.PCBF, "ok"))
    zero = float(res["step_zero_u"][1])
    assert res["step_zero_u"][::2] == [ok_code, "0"]
    for key in ("step_nan_u", "step_minf_u"):
        assert res[key][::2] == [ok_code, "1"], key
        assert abs(float(res[key][1]) - zero) <= 1e-6, key
    assert res["step_null"] == [step_bad]
    assert res["step_ok"] == [str(S.code_of(S.PCBF, "ok")), "1"]


def test_status_codes_have_one_definition(pcbf: dict) -> None:
    header = (pcbf["out"] / "pendulum_pcbf_config.h").read_text()  # statuses: config only
    defined = {m: int(v) for m, v in
               re.findall(r"#define (BAL_[A-Z_]+) \(?(-?\d+)\)?", header)}
    for family in (S.SOLVE, S.PCBF):
        for st in family:
            assert defined[st.macro] == st.code
    m = pcbf["emitted"].manifest
    assert m["status_codes"]["bad_input"] == 5 and m["pcbf_status"]["bad_input"] == 4
    assert len({st.code for st in S.SOLVE}) == len(S.SOLVE)


def test_nan_parameter_through_ctypes_is_bad_input_never_ok(problem: dict) -> None:
    c = CProblem(problem["lib"])
    good = c.pack(_good_filter_params())
    for value in (np.nan, np.inf, -np.inf):
        p = good.copy()
        p[0] = value
        status, f, sol, w = c.solve_packed(p)  # no Python check: the C refuses it
        assert status == "bad_input" and np.isnan(f) and np.isnan(w).all()
    status, f, sol, _ = c.solve_packed(good)
    assert status == "ok" and np.isfinite(f)
    assert status == c.solve(_good_filter_params())[0]


def test_cproblem_solve_checks_names_shapes_and_finiteness(problem: dict) -> None:
    c = CProblem(problem["lib"])
    params = _good_filter_params()
    with pytest.raises(ShapeError, match=r"parameter 'x0': expected shape \(2, 1\), got "
                                         r"shape \(3,\)"):
        c.solve({**params, "x0": np.zeros(3)})
    with pytest.raises(ShapeError, match=r"parameter 'xi': expected shape \(4, 10\), got "
                                         r"shape \(10, 4\)"):
        c.solve({**params, "xi": np.zeros((10, 4))})  # same size, transposed
    with pytest.raises(NonFiniteError, match="parameter 'u_p'"):
        c.solve({**params, "u_p": np.array([np.nan])})
    with pytest.raises(BalustradeError, match="unknown parameters"):
        c.solve({**params, "bogus": 1.0})
    with pytest.raises(BalustradeError, match="no value for parameter 'xi_N'"):
        c.solve({k: v for k, v in params.items() if k != "xi_N"})
    with pytest.raises(BalustradeError, match="parameter 'x0'"):
        c.solve({**params, "x0": "abc"})
    with pytest.raises(ShapeError, match="stacked parameters"):
        c.solve_packed(np.zeros(3))


def test_c_filter_falls_back_as_python_on_nan_state(pcbf: dict) -> None:
    c, py = CPCBFSafetyFilter(pcbf["lib"]), pcbf["py"]
    for x in ([np.nan, 0.0], [0.1, np.inf], [-np.inf, np.nan]):
        for u_p in (2.0, 7.0, -5.0):
            u1, i1 = py.step(np.array(x), np.array([u_p]))
            u2, i2 = c.step(np.array(x), np.array([u_p]))
            assert np.array_equal(u1, u2)
            assert (i1.status, i1.fallback) == (i2.status, i2.fallback) == (
                "non_finite_state", "projected_proposal")
    # a non-finite proposal: read as 0 and filtered, in Python and C alike (the applied
    # input is the filter's for u_p = 0, certified safe; not the bare projection)
    x = np.array([0.45, 1.0])   # outside S_PB: the filter must act
    py.reset()
    u0, _ = py.step(x, np.array([0.0]))
    for u_p in (np.nan, np.inf, -np.inf):
        py.reset()
        c.reset()
        u1, i1 = py.step(x, np.array([u_p]))
        u2, i2 = c.step(x, np.array([u_p]))
        assert np.abs(u1 - u0).max() <= 1e-9 and np.abs(u1 - u2).max() <= 1e-6
        assert (i1.status, i1.fallback) == (i2.status, i2.fallback) == (
            "non_finite_proposal", None)
        assert i1.values["non_finite_proposal"] == i2.values["non_finite_proposal"] == 1.0
    with pytest.raises(ShapeError, match="CPCBFSafetyFilter.step: x"):
        c.step(np.zeros(3), np.array([1.0]))
    with pytest.raises(ShapeError, match="CPCBFSafetyFilter.step: u_p"):
        c.step(np.zeros(2), np.zeros(2))


def test_closed_loop_through_a_nan_measurement_matches_python(pcbf: dict) -> None:
    c, py = CPCBFSafetyFilter(pcbf["lib"]), pcbf["py"]
    py.reset()
    system = pendulum()
    x1 = x2 = np.array([0.3, 0.5])
    for k in range(12):
        meas1, meas2 = (x1, x2) if k != 4 else (np.full(2, np.nan),) * 2
        u1, i1 = py.step(meas1, np.array([2.0]))
        u2, i2 = c.step(meas2, np.array([2.0]))
        assert abs(u1[0] - u2[0]) <= 1e-6 and i1.fallback == i2.fallback, k
        x1, x2 = system.step(x1, u1), system.step(x2, u2)
    assert np.abs(x1 - x2).max() <= 1e-6


def test_emitters_refuse_unwritable_folder_before_casadi(pcbf: dict, tmp_path,
                                                         monkeypatch: pytest.MonkeyPatch
                                                         ) -> None:
    import balustrade.codegen.emit as E

    def no_casadi(*args: object, **kwargs: object) -> None:
        raise AssertionError("CasADi code generation ran")

    monkeypatch.setattr(E, "_generate", no_casadi)
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    bad = blocker / "sub"
    for call in (lambda: emit_pcbf(pcbf["py"], "p", bad),
                 lambda: emit_problem(pcbf["py"].filter, "p", bad),
                 lambda: emit_functions(pendulum().function, "p", bad),
                 lambda: emit_pcbf(pcbf["py"], "p", blocker)):
        with pytest.raises(CodegenError, match="cannot create the output folder.*a_file"):
            call()
    with pytest.raises(CodegenError, match="out_dir must be a path"):
        emit_pcbf(pcbf["py"], "p", None)


def test_emitters_refuse_wrong_objects(pcbf: dict, tmp_path) -> None:
    from balustrade.examples.codegen import pendulum_approximate_filter

    with pytest.raises(CodegenError, match="expected a PCBFSafetyFilter"):
        emit_pcbf(object(), "p", tmp_path)
    with pytest.raises(CodegenError, match="expected a ApproximatePCBFFilter"):
        emit_approximate(pcbf["py"], "p", tmp_path)
    with pytest.raises(CodegenError, match="expected a PCBFSafetyFilter"):
        emit_pcbf(pendulum_approximate_filter(), "p", tmp_path)
    with pytest.raises(CodegenError, match="needs a problem compiled on the CasADi"):
        emit_problem(compile(pcbf["py"].filter.ocp, "cvxpy"), "p", tmp_path)
    with pytest.raises(CodegenError, match="dynamics must be a casadi.Function"):
        emit_pcbf(pcbf["py"], "p", tmp_path, dynamics=pendulum())
    with pytest.raises(CodegenError, match="accept_tol must be finite"):
        emit_problem(pcbf["py"].filter, "p", tmp_path, accept_tol=np.nan)
    with pytest.raises(CodegenError, match="expected a casadi.Function or a dict"):
        emit_functions([pendulum().function], "p", tmp_path)
    em = pcbf["emitted"]
    with pytest.raises(NonFiniteError, match="x_init"):
        write_example(em, [[np.nan, 0.0]], 2.0)
    with pytest.raises(ShapeError, match=r"x_init: expected shape \(n, 2\)"):
        write_example(em, [[0.0, 0.0, 0.0]], 2.0)
    with pytest.raises(CodegenError, match="steps must be a positive integer"):
        write_example(em, [[0.0, 0.0]], 2.0, steps=0)
    with pytest.raises(CodegenError, match="build: .*nowhere.* is not a folder"):
        build(tmp_path / "nowhere")
    with pytest.raises(CodegenError, match="src_dir must be a path"):
        build(None)
    with pytest.raises(CodegenError, match="no 'drv.c'"):
        build_executable(tmp_path, main="drv.c")
    with pytest.raises(CodegenError, match="build: extra_flags must be a tuple of strings"):
        build(tmp_path, extra_flags="-O2")  # not the flags '-', 'O', '2'
    with pytest.raises(CodegenError, match="build_executable: extra_flags must be a tuple"):
        build_executable(tmp_path, extra_flags=[1])
    (tmp_path / "x.json").write_text("{not json")
    with pytest.raises(CodegenError, match="not a readable balustrade manifest"):
        load_manifest(tmp_path, "x")


def test_cli_codegen_reports_bad_output_folder(tmp_path, capsys: pytest.CaptureFixture
                                               ) -> None:
    from balustrade.cli import main

    (tmp_path / "f").write_text("x")
    assert main(["codegen", "pendulum_functions", "--out", str(tmp_path / "f" / "o")]) == 2
    assert "cannot create the output folder" in capsys.readouterr().err
