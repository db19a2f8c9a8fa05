"""The shifted-plan certificate of ``h_PB = 0`` in the emitted PCBF step (issue #14 §3,
C = Python): ``<name>_shift_cert`` is the function :class:`~balustrade.control.shifted.
ShiftedCertificate` evaluates, and bal/pcbf.c takes the decision of
``PCBFSafetyFilter._shifted`` with the same tolerances.

The system is a stable linear 2-state system whose terminal set ``{x' P x <= c}`` (``P``
from the Lyapunov equation of ``A``) is invariant under the zero input, so the shifted plan
(tail input 0) can certify ``h_PB = 0``; on the ``real-time`` preset (2.24) is truncated at
some steps and the certificate replaces the truncated point (measured: it fires at steps
18 and 14, 23, 35 of the two loops below)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg as sla

from balustrade.control import PCBFSafetyFilter, simulate
from balustrade.dsl.sets import Box
from balustrade.dsl.system import LinearSystem

N = 10
A = np.array([[1.0, 0.1], [-0.4, 0.85]])  # spectral radius 0.94
B = np.array([[0.0], [0.5]])
P = sla.solve_discrete_lyapunov(A.T, np.eye(2))
LEVEL = 0.125 / np.max(np.diag(np.linalg.inv(P)))  # the ellipse lies well inside X
STARTS = ([0.5, -1.0], [-0.8, 0.6])
STEPS = 40


def _controller(certificate: bool = True) -> tuple[LinearSystem, PCBFSafetyFilter]:
    system = LinearSystem(A, B, name="stable2")
    X, U = Box([-1.0, -1.5], [1.0, 1.5]), Box([-2.0], [2.0])
    ctl = PCBFSafetyFilter.build(system, X, U, lambda x: x.T @ P @ x - LEVEL, N,
                                       1e-3 * np.arange(N), target="real-time")
    # the certificate checked after (2.24) (this file's subject), not before it as by
    # default (certificate_first: tests/test_certificate_first.py)
    ctl = PCBFSafetyFilter(ctl.slack, ctl.filter, U, shifted_certificate=certificate,
                           certificate_first=False)
    return system, ctl


@pytest.fixture(scope="module")
def cert_c(tmp_path_factory):
    from balustrade.codegen import CPCBFSafetyFilter, build, emit_pcbf

    system, py = _controller()
    out = tmp_path_factory.mktemp("cert_pcbf")
    emitted = emit_pcbf(py, "certpcbf", out)
    lib = build(out, emitted.name, werror=True)
    return {"system": system, "py": py, "c": CPCBFSafetyFilter(lib), "emitted": emitted,
            "out": out}


def _loops(system, ctl):
    rng = np.random.default_rng(7)
    runs = []
    for x0 in STARTS:
        proposals = rng.uniform(-3.0, 3.0, size=STEPS)
        ctl.reset()
        runs.append(simulate(system, ctl, x0, STEPS, keep_infos=True,
                             proposal=lambda k, x, p=proposals: np.array([p[k] + 1.5])))
    return runs


def _fired(trace) -> list[int]:
    return [k for k, i in enumerate(trace.infos) if i.values.get("shifted_certificate")]


def test_manifest_and_config_name_the_certificate(cert_c):
    assert cert_c["emitted"].manifest["shifted_certificate"] is True
    assert cert_c["c"].shifted_certificate
    config = (cert_c["out"] / "certpcbf_config.h").read_text()
    assert "#define certpcbf_SHIFT_CERT 1" in config
    assert "certpcbf_shift_cert" in (cert_c["out"] / "certpcbf_casadi.c").read_text()


def test_c_certifies_the_shifted_plan_exactly_as_python(cert_c):
    """C = Python on real-time loops where the certificate fires: the same steps fire, the
    same statuses, fallbacks, h_PB and solver costs, inputs within 1e-6. Fails if the C
    does not evaluate the certificate (it then keeps the truncated (2.24))."""
    system = cert_c["system"]
    fired = 0
    for t1, t2 in zip(_loops(system, cert_c["py"]), _loops(system, cert_c["c"])):
        assert _fired(t1) == _fired(t2)
        fired += len(_fired(t2))
        assert [i.status for i in t1.infos] == [i.status for i in t2.infos]
        assert t1.fallbacks == t2.fallbacks
        assert [i.uncertified for i in t1.infos] == [i.uncertified for i in t2.infos]
        for a, b in zip(t1.infos, t2.infos):
            assert sorted(a.values) == sorted(b.values)
            for key in a.values:
                np.testing.assert_allclose(b.values[key], a.values[key], atol=1e-6,
                                           equal_nan=True)
        assert np.abs(t1.inputs - t2.inputs).max() <= 1e-6
    assert fired >= 1  # the certificate fired in both


def test_certificate_off_is_emitted_off_and_said(tmp_path):
    """A controller built with shifted_certificate=False emits a step without it, and the
    manifest and the runtime say so."""
    from balustrade.codegen import CPCBFSafetyFilter, build, emit_pcbf

    system, py = _controller(certificate=False)
    emitted = emit_pcbf(py, "nocert", tmp_path)
    assert emitted.manifest["shifted_certificate"] is False
    assert "#define nocert_SHIFT_CERT 0" in (tmp_path / "nocert_config.h").read_text()
    c = CPCBFSafetyFilter(build(tmp_path, emitted.name, werror=True))
    assert not c.shifted_certificate
    t = _loops(system, c)[1]
    assert not _fired(t)
    # the bare deployment spec carries the choice (review: it always got a certificate)
    spec = py.deployment_spec()
    assert spec.shifted_certificate is False
    emitted_spec = emit_pcbf(spec, "nocert2", tmp_path / "spec")
    assert emitted_spec.manifest["shifted_certificate"] is False


DRIVER = r"""
/* Replays the states and proposals of a Python loop through the emitted step. */
#include <stdio.h>
#include "certpcbf.h"
#include "replay.h"

int main(void) {
  certpcbf_work* wk = certpcbf_alloc();
  casadi_real u[certpcbf_NU], h;
  int k, st, fired = 0;
  if (!wk) return 1;
  for (k = 0; k < REPLAY_K; ++k) {
    certpcbf_step(REPLAY_X[k], REPLAY_U + k, u, &h, &st, wk);
    fired += certpcbf_shift_certified(wk);
    printf("%d %.17g\n", st, u[0]);
  }
  printf("fired %d\n", fired);
  certpcbf_free(wk);
  return 0;
}
"""


def test_certificate_path_is_memory_clean_under_valgrind(cert_c):
    """The C step replays a Python loop in which the certificate fires, from a driver
    without Python (under valgrind when installed): the same inputs, no memory error."""
    import shutil
    import subprocess

    from balustrade.codegen import build_executable

    rng = np.random.default_rng(7)
    rng.uniform(-3.0, 3.0, size=STEPS)  # the proposals of the first loop
    proposals = rng.uniform(-3.0, 3.0, size=STEPS) + 1.5
    py = cert_c["py"]
    py.reset()
    trace = simulate(cert_c["system"], py, STARTS[1], STEPS, keep_infos=True,
                     proposal=lambda k, x: np.array([proposals[k]]))
    assert _fired(trace)
    out = cert_c["out"]
    rows = ",\n".join("{" + ", ".join(f"{v:.17g}" for v in x) + "}"
                      for x in np.asarray(trace.states)[:STEPS])
    (out / "replay.h").write_text(
        f"#define REPLAY_K {STEPS}\nstatic const casadi_real REPLAY_X[{STEPS}][2] = "
        f"{{{rows}}};\nstatic const casadi_real REPLAY_U[{STEPS}] = "
        f"{{{', '.join(f'{v:.17g}' for v in proposals)}}};\n")
    (out / "driver.c").write_text(DRIVER)
    cmd = [str(build_executable(out, main="driver.c", werror=True))]
    if shutil.which("valgrind"):
        cmd = ["valgrind", "--error-exitcode=9", "--leak-check=full", "-q", *cmd]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600, check=False)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert lines[-1] == f"fired {len(_fired(trace))}"
    u_c = np.array([float(line.split()[1]) for line in lines[:-1]])
    assert np.abs(u_c - np.asarray(trace.inputs).reshape(-1)).max() <= 1e-6
