"""The static C of the emitted code (package data in ``balustrade/codegen/c/``), the generated
config headers that instantiate it, statuses defined once, and typed deployment specs."""

from __future__ import annotations

import ctypes
import re
import subprocess
from pathlib import Path

import numpy as np
import pytest

from balustrade.codegen import build, emit_approximate, emit_pcbf, emit_problem, find_compiler
from balustrade.codegen import cfiles as C
from balustrade.codegen import status as S
from balustrade.control.deploy import ApproximateDeployment, PCBFDeployment
from balustrade.errors import CodegenError
from balustrade.examples.codegen import pendulum_approximate_filter, pendulum_pcbf_filter

PACKAGED = (*C.STATIC, "example_main.c", "casadi_prologue.h", "Makefile.in")


@pytest.fixture(scope="module")
def modules(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A problem, a PCBF step and an Algorithm 7.5 step, emitted into one folder."""
    out = tmp_path_factory.mktemp("cfiles")
    pcbf = pendulum_pcbf_filter()
    approx = pendulum_approximate_filter()
    return {"out": out, "pcbf_ctrl": pcbf, "approx_ctrl": approx,
            "problem": emit_problem(pcbf.filter, "filt", out),
            "pcbf": emit_pcbf(pcbf, "pcbf", out),
            "approx": emit_approximate(approx, "approx", out)}


def test_static_files_are_package_data() -> None:
    for fname in PACKAGED:
        assert C.static_path(fname).is_file(), fname
    text = Path(__file__).resolve().parent.parent.joinpath("pyproject.toml").read_text()
    assert '"balustrade.codegen" = ["c/*.c", "c/*.h", "c/Makefile.in"]' in text


def test_static_files_copied_unchanged(modules: dict) -> None:
    em = modules["pcbf"]
    assert sorted(p.name for p in em.static) == sorted(C.STATIC)
    for path in em.static:
        assert path.read_text() == C.static_text(path.name), path.name


def test_generated_files_hold_no_code(modules: dict) -> None:
    """The generated config header is comments and #defines only, the glue only
    #define/#include/#undef: every decision of the emitted C is in the static files."""
    out = modules["out"]
    allowed = re.compile(r"^(#(define|ifndef|endif|undef|include|ifdef)\b|/\*| \*|\s*$|"
                         r"  .*\\$|  .*\}$|extern \"C\" \{$|\} /\* extern)")
    for name in ("filt", "pcbf", "approx"):
        for fname in (f"{name}_config.h", f"{name}.h", f"{name}.c"):
            for line in (out / fname).read_text().splitlines():
                assert allowed.match(line), f"{fname}: generated code line {line!r}"


def test_each_module_builds_pedantic_with_werror(modules: dict) -> None:
    """Each static .c file, instantiated by its generated config, compiles as strict C99
    with -Wall -Wextra -Werror (problem.c alone, pcbf.c and approx.c with their problems)."""
    cc, out = find_compiler(), modules["out"]
    for name in ("filt", "pcbf", "approx"):
        subprocess.run([cc, "-std=c99", "-pedantic", "-Wall", "-Wextra", "-Wshadow", "-Werror",
                        "-fsyntax-only", str(out / f"{name}.c")], check=True, cwd=out)


def test_entry_points_listed_in_the_header_are_exported(modules: dict) -> None:
    """The names the generated header lists (``cfiles.ENTRY_POINTS``) are the symbols the
    static C defines under the module's prefixes."""
    out = modules["out"]
    lib = ctypes.CDLL(str(build(out, "filt_pcbf_approx", werror=True)))
    parts = {"filt": [("problem", "filt_p")],
             "pcbf": [("problem", "pcbf_slack"), ("problem", "pcbf_filter"), ("pcbf", "pcbf")],
             "approx": [("problem", "approx_dec"), ("problem", "approx_filter"),
                        ("approx", "approx")]}
    for name, prefixes in parts.items():
        header = (out / f"{name}.h").read_text()
        for kind, prefix in prefixes:
            for entry in C.ENTRY_POINTS[kind]:
                sym = f"{prefix}_{entry}"
                assert re.search(rf"\b{sym}\b", header), (name, sym)
                assert hasattr(lib, sym), sym


def test_status_codes_defined_once() -> None:
    """The static C only uses status macros: every BAL_* name it uses is a status of
    :mod:`balustrade.codegen.status` or a macro of bal/common.h, and no static file defines
    a status (the generated config does, from the tables)."""
    statuses = {st.macro for fam in (S.SOLVE, S.PCBF, S.APPROX) for st in fam}
    common = C.static_text("common.h")
    own = set(re.findall(r"#define (BAL_[A-Z0-9_]+)", common))
    for fname in PACKAGED:
        text = C.static_text(fname)
        defined = set(re.findall(r"#define (BAL_[A-Z0-9_]+)", text))
        assert not defined & statuses, (fname, defined & statuses)
        own |= defined
    for fname in PACKAGED:
        used = set(re.findall(r"\bBAL_[A-Z0-9_]*[A-Z0-9]\b", C.static_text(fname)))
        used -= {"BAL_PROBLEM", "BAL_STEP"}  # the prefixes the glue defines
        assert used <= statuses | own, (fname, used - statuses - own)
    for fam in (S.SOLVE, S.PCBF, S.APPROX):
        assert len({st.code for st in fam}) == len(fam)
        assert len({st.name for st in fam}) == len(fam)


def test_config_status_block_matches_tables(modules: dict) -> None:
    text = (modules["out"] / "approx_config.h").read_text()
    defined = {m: int(v) for m, v in re.findall(r"#define (BAL_[A-Z_]+) \(?(-?\d+)\)?", text)}
    for fam in (S.SOLVE, S.APPROX):
        for st in fam:
            assert defined[st.macro] == st.code


def test_two_modules_in_one_translation_unit(modules: dict) -> None:
    """Headers of several modules can be included together (guarded status blocks,
    prefix macros undefined after use)."""
    out = modules["out"]
    (out / "both.c").write_text('#include "pcbf.h"\n#include "approx.h"\n#include "filt.h"\n'
                                "int both_ok(void) { return BAL_OK + BAL_PCBF_OK + "
                                "BAL_APPROX_OK + pcbf_NX + approx_NX + filt_p_NP; }\n")
    try:
        subprocess.run([find_compiler(), "-std=c99", "-Wall", "-Wextra", "-Werror",
                        "-fsyntax-only", str(out / "both.c")], check=True, cwd=out)
    finally:
        (out / "both.c").unlink()


def test_deployment_specs_are_typed() -> None:
    pcbf = pendulum_pcbf_filter()
    spec = pcbf.deployment_spec()
    assert isinstance(spec, PCBFDeployment)
    assert spec.slack is pcbf.slack and spec.filter is pcbf.filter and spec.U is pcbf.U
    approx = pendulum_approximate_filter()
    spec = approx.deployment_spec()
    assert isinstance(spec, ApproximateDeployment)
    assert spec.decrease is approx.decrease.compiled and spec.filter is approx.filter
    assert spec.grid.shape[1] == approx.nu and spec.n_local == approx.decrease.n_local


def test_emitters_read_only_the_spec(modules: dict, tmp_path) -> None:
    """An emitter takes a spec itself, and reads nothing else from a controller: an object
    that only answers deployment_spec() emits the same C."""
    spec = modules["pcbf_ctrl"].deployment_spec()

    class OnlySpec:
        def deployment_spec(self) -> PCBFDeployment:
            return spec

    a = emit_pcbf(spec, "pcbf", tmp_path / "a")
    b = emit_pcbf(OnlySpec(), "pcbf", tmp_path / "b")
    for fname in ("pcbf_config.h", "pcbf.h", "pcbf.c"):
        ref = (modules["out"] / fname).read_text()
        assert (a.out_dir / fname).read_text() == ref == (b.out_dir / fname).read_text()
    with pytest.raises(CodegenError, match="expected a PCBFSafetyFilter"):
        emit_pcbf(modules["approx_ctrl"].deployment_spec(), "p", tmp_path)
    assert np.array_equal(modules["approx"].manifest["U"]["lb"], [-3.0])


def test_emit_problem_docstring_names_the_generated_entry_points(modules: dict) -> None:
    """Every ``<name>_p_*`` the docstring of emit_problem names is generated (header entry
    point, work struct or offset macro of the config)."""
    doc = emit_problem.__doc__
    named = set(re.findall(r"<name>_p_(\w+)", doc))
    assert {"solve", "work", "init", "W_u"} <= named
    out = modules["out"]
    text = (out / "filt.h").read_text() + (out / "filt_config.h").read_text()
    for entry in named:
        if entry.startswith("_"):  # "<name>_p_init``/``_finalize": a list, checked below
            continue
        assert re.search(rf"\bfilt_p_{entry}\b", text), entry
    assert not re.search(r"<name>_(solve|work|W_)", doc)


def test_emit_problems_module_equals_single_problems(modules: dict, tmp_path) -> None:
    """Several problems in one module (prefix <name>_<key>) solve as emit_problem's."""
    from balustrade.codegen import CProblem, emit_problems

    ctrl = modules["pcbf_ctrl"]
    em = emit_problems({"slack": ctrl.slack, "filter": ctrl.filter}, "pair", tmp_path)
    assert em.kind == "problems" and set(em.manifest["problems"]) == {"slack", "filter"}
    lib = build(tmp_path, "pair", werror=True)
    pair = CProblem(lib, problem="filter")
    single = CProblem(build(modules["out"], werror=True, out=tmp_path / "libsingle.so"),
                      modules["problem"].manifest)
    params = {"x0": np.array([0.1, 0.2]), "u_p": np.array([2.0]), "xi": np.zeros((4, 10)),
              "xi_N": 0.0}
    a, b = pair.solve(params, warm=False), single.solve(params, warm=False)
    assert a[0] == b[0] == "ok" and a[1] == b[1] and np.array_equal(a[3], b[3])
    # <P>_residuals writes three values (primal, dual, scaled violation): the runtime's
    # buffer must hold all three, and residuals() returns the first two
    out = np.full(4, np.nan)
    fn = ctypes.CDLL(str(lib))["pair_filter_residuals"]
    fn.argtypes, fn.restype = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_double)], None
    fn(pair.view.work, out.ctypes.data_as(ctypes.POINTER(ctypes.c_double)))
    assert np.all(np.isfinite(out[:3])) and np.isnan(out[3])
    assert pair.view.residuals() == (out[0], out[1]) and pair.view._res.size == 3
    with pytest.raises(CodegenError, match="no emitted problem 'nope'"):
        CProblem(lib, problem="nope")


def test_robust_controller_problems_emit_through_its_spec(unstable2d_tube, tmp_path) -> None:
    """Algorithm 5.2 has no emitted step: its ProblemsDeployment ((5.15), (5.16)) emits as
    one module of two problems that builds with -Werror."""
    from balustrade.codegen import emit_problems
    from balustrade.control.deploy import ProblemsDeployment
    from balustrade.control.robust import RobustPCBFSafetyFilter

    t = unstable2d_tube
    s = t["s"]
    ctrl = RobustPCBFSafetyFilter.build(t["system"], s.X, s.U, t["cbf"], t["cbf"].policy,
                                        t["N"], s.deltas(), t["error"], s.alpha_f,
                                        target="robust-sqp", slack_target="robust-sqp")
    spec = ctrl.deployment_spec()
    assert isinstance(spec, ProblemsDeployment) and spec.problems["slack"] is ctrl.slack
    em = emit_problems(ctrl, "robust", tmp_path)
    header = (tmp_path / "robust.h").read_text()
    assert "robust_slack_solve" in header and "robust_filter_solve" in header
    build(tmp_path, "robust", werror=True)
    assert em.manifest["problems"]["filter"]["prefix"] == "robust_filter"
