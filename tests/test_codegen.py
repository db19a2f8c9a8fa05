"""C code generation (issue 6): the emitted C gives the answers of the Python CasADi backend.

Everything is emitted and compiled once per module (tmp dir), with -Werror.
"""

from __future__ import annotations

import shutil
import subprocess

import casadi as ca
import numpy as np
import pytest

from balustrade.backends import compile
from balustrade.codegen import (
    CFunction,
    CPCBFSafetyFilter,
    CProblem,
    build,
    build_executable,
    emit_function,
    emit_pcbf,
    emit_problem,
    find_compiler,
)
from balustrade.codegen.build import run_under_valgrind
from balustrade.codegen.runtime import mirror_c_retries
from balustrade.control.base import simulate
from balustrade.errors import BalustradeError, CodegenError, ShapeError
from balustrade.examples.codegen import (
    PENDULUM_X0,
    emit_pendulum_pcbf,
    pendulum_functions,
    pendulum_pcbf_filter,
)
from balustrade.models.pendulum import pendulum

N_STATES = 1000


@pytest.fixture(scope="module")
def pcbf_c(tmp_path_factory: pytest.TempPathFactory) -> dict:
    out = tmp_path_factory.mktemp("pendulum_pcbf")
    emitted = emit_pendulum_pcbf(out)
    lib = build(out, emitted.name, werror=True)
    py = pendulum_pcbf_filter()
    default = pendulum_pcbf_filter()  # the Python backend as shipped (IPOPT last resort)
    # the reference: the Python backend with the retries of the C (eigen-clip, not IPOPT)
    py.slack = mirror_c_retries(py.slack)
    py.filter = mirror_c_retries(py.filter)
    return {"out": out, "emitted": emitted, "lib": lib, "py": py, "default": default}


@pytest.fixture(scope="module")
def functions_c(tmp_path_factory: pytest.TempPathFactory) -> dict:
    from balustrade.codegen import emit_functions

    out = tmp_path_factory.mktemp("pendulum_functions")
    fns = pendulum_functions()
    emitted = emit_functions(fns, "pendfun", out)
    lib = build(out, emitted.name, werror=True)
    return {"fns": fns, "lib": lib}


def _random_states(seed: int, n: int = N_STATES) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    # X = [-0.5, 0.5] x [-1.5, 1.5]: sample inside, on and beyond the boundary
    return rng.uniform([-0.7, -2.0], [0.7, 2.0], size=(n, 2)), rng.uniform(-4, 4, size=(n, 1))


def test_pcbf_step_equals_python_on_1000_states(pcbf_c: dict) -> None:
    c = CPCBFSafetyFilter(pcbf_c["lib"])
    py = pcbf_c["py"]
    X, UP = _random_states(0)
    du, dh = [], []
    for x, u_p in zip(X, UP):
        py.reset()
        c.reset()
        u1, i1 = py.step(x, u_p)
        u2, i2 = c.step(x, u_p)
        assert i1.fallback == i2.fallback, (x, u_p, i1.status, i2.status)
        h1, h2 = i1.values.get("h_PB", np.nan), i2.values.get("h_PB", np.nan)
        assert np.isnan(h1) == np.isnan(h2)
        du.append(abs(u1 - u2).max())
        if np.isfinite(h1):
            dh.append(abs(h1 - h2))
    assert max(du) <= 1e-6, max(du)
    assert max(dh) <= 1e-6, max(dh)


def test_single_problem_equals_python_on_1000_states(pcbf_c: dict,
                                                     tmp_path_factory: pytest.TempPathFactory
                                                     ) -> None:
    slack = pcbf_c["py"].slack
    out = tmp_path_factory.mktemp("slack")
    emitted = emit_problem(slack, "slack", out)
    assert "slack_p_solve" in (out / "slack.h").read_text()
    prob = CProblem(build(out, emitted.name, werror=True))
    X, _ = _random_states(1)
    for x in X:
        sol = slack.solve({"x0": x})
        status, value, primal, w = prob.solve({"x0": x}, warm=False)
        assert (status in ("ok", "feasible")) == sol.success, (x, status, sol.status)
        if sol.success:
            assert abs(value - sol.objective) <= 1e-6
            assert abs(primal["u"][0, 0] - sol["u"][0, 0]) <= 1e-6
            assert np.abs(w[: slack.layout.user_size] - sol.w).max() <= 1e-6


def test_plain_functions_equal_casadi_to_1e12(functions_c: dict) -> None:
    rng = np.random.default_rng(2)
    fns = functions_c["fns"]
    for sym, fn in fns.items():
        cfn = CFunction(functions_c["lib"], sym)
        for _ in range(N_STATES):
            args = [rng.normal(size=(fn.size1_in(i), fn.size2_in(i))) for i in range(fn.n_in())]
            want = [np.asarray(v) for v in fn.call([ca.DM(a) for a in args])]
            got = cfn(*args)
            for a, b in zip(want, got):
                assert np.abs(a.reshape(b.shape) - b).max() <= 1e-12, sym


def test_plain_function_refuses_wrong_inputs(functions_c: dict) -> None:
    cfn = CFunction(functions_c["lib"], "dynamics")
    with pytest.raises(ShapeError, match=r"dynamics: input 0: expected shape \(2, 1\), got "
                                         r"shape \(3,\)"):
        cfn(np.zeros(3), np.zeros(1))
    with pytest.raises(BalustradeError, match="input 1 must be numbers"):
        cfn(np.zeros(2), "u")
    with pytest.raises(CodegenError, match="expected 2 inputs, got 1"):
        cfn(np.zeros(2))


def test_closed_loop_with_c_filter_matches_python(pcbf_c: dict) -> None:
    system = pendulum()
    py = pcbf_c["py"]
    c = CPCBFSafetyFilter(pcbf_c["lib"])
    rng = np.random.default_rng(3)
    starts = np.vstack([PENDULUM_X0, rng.uniform([-0.5, -1.5], [0.5, 1.5], size=(4, 2))])
    for x0 in starts:
        for proposal in (2.0, lambda k, x: 3.5 * np.sin(0.4 * k)):
            py.reset()
            c.reset()
            t1 = simulate(system, py, x0, 40, proposal=proposal)
            t2 = simulate(system, c, x0, 40, proposal=proposal)
            assert t1.states.shape == t2.states.shape
            assert np.abs(t1.states - t2.states).max() <= 1e-6
            assert np.abs(t1.inputs - t2.inputs).max() <= 1e-6
            assert t1.fallbacks == t2.fallbacks
            assert np.allclose(t1.values["h_PB"], t2.values["h_PB"], atol=1e-6,
                               equal_nan=True)


def test_closed_loop_with_c_filter_matches_default_python(pcbf_c: dict) -> None:
    """Against the backend as shipped (IPOPT as the last retry, where the C uses
    eigen-clip sqpmethod): equal to 1e-6 with the example's proposal u_p = 2; with a
    proposal pushing at the constraints, where qrqp needs retries, to solver accuracy."""
    system = pendulum()
    py, c = pcbf_c["default"], CPCBFSafetyFilter(pcbf_c["lib"])
    rng = np.random.default_rng(4)
    starts = np.vstack([PENDULUM_X0, rng.uniform([-0.5, -1.5], [0.5, 1.5], size=(6, 2))])
    for x0 in starts:
        for proposal, tol in ((2.0, 1e-6), (lambda k, x: 3.5 * np.sin(0.4 * k), 1e-5)):
            py.reset()
            c.reset()
            t1 = simulate(system, py, x0, 40, proposal=proposal)
            t2 = simulate(system, c, x0, 40, proposal=proposal)
            assert np.abs(t1.states - t2.states).max() <= tol
            assert np.abs(t1.inputs - t2.inputs).max() <= tol
            assert t1.fallbacks == t2.fallbacks


def test_c_filter_fallbacks_never_raise(pcbf_c: dict) -> None:
    c = CPCBFSafetyFilter(pcbf_c["lib"])
    u, info = c.step(np.array([np.nan, 0.0]), np.array([7.0]))
    assert info.fallback == "projected_proposal" and u[0] == 3.0
    assert info.status == "non_finite_state"


def test_main_example_builds_with_werror_and_runs(pcbf_c: dict) -> None:
    exe = build_executable(pcbf_c["out"])  # -Wall -Wextra -Werror
    proc = subprocess.run([str(exe), "200"], capture_output=True, text=True, check=True)
    bench = dict(line.split()[1:3] for line in proc.stdout.splitlines()
                 if line.startswith("BENCH"))
    assert float(bench["pcbf_step_median_us"]) > 0
    assert "# closed loop 0" in proc.stdout


@pytest.mark.skipif(shutil.which("valgrind") is None, reason="valgrind not installed")
def test_main_example_clean_under_valgrind(pcbf_c: dict) -> None:
    exe = pcbf_c["out"] / "main"
    if not exe.exists():
        exe = build_executable(pcbf_c["out"])
    proc = run_under_valgrind(str(exe), "10")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "ERROR SUMMARY: 0 errors" in proc.stderr


def test_makefile_and_sources_written(pcbf_c: dict) -> None:
    out = pcbf_c["out"]
    for f in ("Makefile", "main.c", "pendulum_pcbf.c", "pendulum_pcbf.h",
              "pendulum_pcbf_casadi.c", "pendulum_pcbf_casadi.h", "pendulum_pcbf.json"):
        assert (out / f).is_file(), f
    # the header declares the step under its real name (through the static bal/pcbf.h)
    proc = subprocess.run([find_compiler(), "-E", "-P", str(out / "pendulum_pcbf.h")],
                          capture_output=True, text=True, check=True)
    header = " ".join(proc.stdout.split())
    assert "int pendulum_pcbf_step(const double* x, const double* u_p" in header
    assert "-Werror" in (out / "Makefile").read_text()


def _doc_block(lang: str, after: str) -> str:
    from pathlib import Path

    text = (Path(__file__).resolve().parent.parent / "docs" / "deploy_c.md").read_text()
    rest = text[text.index(after):]
    start = rest.index(f"```{lang}\n") + len(lang) + 4
    return rest[start: rest.index("```", start)]


def test_docs_c_snippet_builds_and_runs(pcbf_c: dict) -> None:
    out = pcbf_c["out"]
    (out / "my_controller.c").write_text(_doc_block("c", "## 2. Call the filter"))
    cc = find_compiler()
    exe = out / "my_controller"
    # the documented command compiles the generated sources too; linking the library built
    # from them by the fixture is the same code and saves a compile
    subprocess.run([cc, "-O3", "-Wall", "-Wextra", "-Werror", "-o", str(exe),
                    str(out / "my_controller.c"), f"-L{out}", "-lpendulum_pcbf",
                    f"-Wl,-rpath,{out}", "-lm"], check=True)
    (out / "my_controller.c").unlink()
    proc = subprocess.run([str(exe)], capture_output=True, text=True, check=True)
    assert proc.stdout.startswith("apply u = ")


def test_docs_python_snippet_runs(pcbf_c: dict, tmp_path) -> None:
    src = tmp_path / "pendulum_pcbf"  # a copy: the snippet rebuilds the library in place
    shutil.copytree(pcbf_c["out"], src, ignore=shutil.ignore_patterns("*.so", "main"))
    code = _doc_block("python", "## 3. Simulate in Python")
    code = code.replace('build("out/pendulum_pcbf")', f'build("{src}")')
    exec(code, {})  # noqa: S102 - the documented snippet, as a user runs it


# -- refusals ----------------------------------------------------------------------------
def test_refuses_ipopt(pcbf_c: dict, tmp_path) -> None:
    ocp = pcbf_c["py"].slack.ocp
    with pytest.raises(CodegenError, match="ipopt.*sqpmethod"):
        emit_problem(compile(ocp, "casadi", "ipopt"), "s", tmp_path)


def test_refuses_qpoases_and_external_libraries(pcbf_c: dict, tmp_path) -> None:
    ocp = pcbf_c["py"].slack.ocp
    opts = {"qpsol": "qpoases", "qpsol_options": {"printLevel": "none"}}
    with pytest.raises(CodegenError, match="qpoases"):
        emit_problem(compile(ocp, "casadi", "sqpmethod", opts), "s", tmp_path)
    osqp = compile(ocp, "casadi", "sqpmethod", {"qpsol": "osqp",
                                                "qpsol_options": {"osqp": {"verbose": False}}})
    with pytest.raises(CodegenError, match="libosqp"):
        emit_problem(osqp, "s", tmp_path)
    emitted = emit_problem(osqp, "s", tmp_path, allow_external=True)  # emitted, not built
    assert emitted.libraries == ("osqp",) and emitted.manifest["libraries"] == ["osqp"]


def test_refuses_cvxpy_backend(pcbf_c: dict, tmp_path) -> None:
    with pytest.raises(CodegenError, match="CasADi backend"):
        emit_problem(compile(pcbf_c["py"].slack.ocp, "cvxpy"), "s", tmp_path)


class _Twice(ca.Callback):
    def __init__(self) -> None:
        ca.Callback.__init__(self)
        self.construct("twice", {"enable_fd": True})

    def get_n_in(self) -> int:
        return 1

    def get_n_out(self) -> int:
        return 1

    def eval(self, arg: list) -> list:
        return [2 * arg[0]]


def test_refuses_python_callback(tmp_path) -> None:
    cb = _Twice()
    x = ca.MX.sym("x")
    f = ca.Function("f", [x], [cb(x) + x])
    with pytest.raises(CodegenError, match="Callback"):
        emit_function(f, "f", tmp_path)
    nested = ca.Function("g", [x], [f(ca.sin(x))])
    with pytest.raises(CodegenError, match="g -> f -> twice"):
        emit_function(nested, "g", tmp_path)
    nlp = ca.nlpsol("s", "sqpmethod", {"x": x, "f": cb(x) ** 2},
                    {"qpsol": "qrqp", "print_time": False})
    with pytest.raises(CodegenError, match="Callback"):
        emit_function(nlp, "s", tmp_path)


def test_refuses_missing_compiler(monkeypatch: pytest.MonkeyPatch, tmp_path) -> None:
    monkeypatch.setenv("CC", "/nonexistent/bin/cc")
    with pytest.raises(CodegenError, match="nonexistent"):
        find_compiler()
    emitted = emit_function(pendulum().function, "dyn", tmp_path)
    with pytest.raises(CodegenError, match="C compiler"):
        build(emitted.out_dir)
    monkeypatch.delenv("CC")
    monkeypatch.setenv("PATH", str(tmp_path))
    with pytest.raises(CodegenError, match="no C compiler"):
        find_compiler()


def test_refuses_non_box_input_set_and_bad_names(pcbf_c: dict, tmp_path) -> None:
    from dataclasses import replace

    from balustrade.dsl.sets import Polytope

    # the emitters read the controller's typed deployment spec: one with a polytope U
    spec = replace(pcbf_c["py"].deployment_spec(),
                   U=Polytope(np.array([[1.0], [-1.0]]), np.array([3.0, 3.0])))
    with pytest.raises(CodegenError, match="Box"):
        emit_pcbf(spec, "p", tmp_path)
    with pytest.raises(CodegenError, match="identifier"):
        emit_pcbf(pcbf_c["py"], "not a name", tmp_path)


def test_cli_codegen_writes_sources(tmp_path, capsys: pytest.CaptureFixture) -> None:
    from balustrade.cli import main

    assert main(["codegen", "list"]) == 0
    assert "pendulum_pcbf" in capsys.readouterr().out
    assert main(["codegen", "pendulum_functions", "--out", str(tmp_path / "f")]) == 0
    assert (tmp_path / "f" / "pendulum_functions_casadi.c").is_file()
    assert main(["codegen", "nope"]) == 2
