"""The emitted Algorithm 6.4 with (6.15g) in running-sum form (``running_sum=True``, the
form of the lane change, §8.2) decides as its Python controller: the C starts (6.15) from
the candidate with the candidate's running sums, as Python does (``bal/multiobj.c``,
``<name>_XI_SUM``), and the inputs, statuses, fallbacks and values agree along closed loops
of the 2-D example (the check of ``tests/test_emit_robust.py`` on the other form)."""

from __future__ import annotations

import numpy as np
import pytest
from test_emit_robust import N, _design, _kind, _same_mo

from balustrade.codegen import CMultiobjectivePCBFFilter, build, emit_multiobjective
from balustrade.codegen.emit_robust import EMITTABLE_TARGET
from balustrade.codegen.runtime import mirror_c_retries
from balustrade.control.multiobjective import MultiobjectivePCBFController
from balustrade.models.unstable2d import W_BOUND, unstable2d, unstable2d_setup


@pytest.fixture(scope="module")
def pair(tmp_path_factory: pytest.TempPathFactory) -> dict:
    system, s = unstable2d(), unstable2d_setup(N)
    base, _ = _design()
    py = MultiobjectivePCBFController.build(
        system, s.X, s.U, base.h_f, base.pi_f, N, s.deltas(), base.error, s.alpha_f,
        target=EMITTABLE_TARGET, slack_target=EMITTABLE_TARGET, running_sum=True)
    py.slack, py.problem = mirror_c_retries(py.slack), mirror_c_retries(py.problem)
    out = tmp_path_factory.mktemp("multiobj_sum_c")
    emitted = emit_multiobjective(py, "mos", out)
    return {"py": py, "c": CMultiobjectivePCBFFilter(build(out, emitted.name, werror=True)),
            "system": system, "manifest": emitted.manifest}


def test_running_sum_c_equals_python_along_closed_loops(pair: dict) -> None:
    py, c, system = pair["py"], pair["c"], pair["system"]
    assert "xi_sum" in py.problem.ocp.variables
    rng = np.random.default_rng(3)
    starts = [unstable2d_setup(N).x0, *rng.uniform([-0.8, -5.0], [0.8, 5.0], (5, 2))]
    seen: dict[str, int] = {}
    w = W_BOUND * np.ones(2)
    for k, x in enumerate(starts):
        py.reset()
        c.reset()
        for j in range(6):
            out_py, out_c = py.step(x, [2.5]), c.step(x, [2.5])
            assert _kind(out_py[1].status) == _kind(out_c[1].status), (k, j)
            _same_mo(out_py, out_c, f"start {k}, step {j}")
            seen[str(out_c[1].fallback)] = seen.get(str(out_c[1].fallback), 0) + 1
            x = system.step(x, out_py[0], w)
    assert seen.get("None", 0) >= 10 and seen.get("warm_start", 0) >= 5, seen
