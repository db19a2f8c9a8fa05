"""Algorithm 4.1 in C reads IPOPT's acceptable stop as :class:`~balustrade.control.rapsf.RAPSF`
does (session 14; the flag ``<P>_inaccurate`` of session 13, tests/test_ipopt_status.py).

RAPSF uses only an ``optimal`` (4.5); a solve that ends ``optimal_inaccurate`` (IPOPT's
``Solved_To_Acceptable_Level``) is recorded in ``uncertified`` and handled as a failed one
(stored plan or backup). The emitted IPOPT returns 0 for that stop as for success, so the
C applied that plan and said ``ok`` where Python fell back. Now ``bal/rapsf.c`` does not use
such a ``BAL_OK`` (``<name>_inaccurate``) and :class:`~balustrade.codegen.CRAPSF` names it
``optimal_inaccurate``.

The 2-state toy of tests/conftest.py, N = 5, (4.5) on IPOPT alone: once with a tolerance it
cannot meet and one acceptable iterate enough (every solve stops at the acceptable level;
the emitted C keeps those options, as tests/test_ipopt_status.py does), once converging."""

from __future__ import annotations

import numpy as np
import pytest
from test_ipopt_status import ACCEPTABLE

from balustrade.backends.emittable import STATUS_OPTIONS
from balustrade.backends.targets import Target
from balustrade.codegen import CRAPSF, build, emit_rapsf
from balustrade.codegen import emit as E
from balustrade.codegen.emit_rapsf import link_flags
from balustrade.control.rapsf import RAPSF

N = 5


@pytest.fixture(scope="module")
def pairs(rapsf_toy, tmp_path_factory: pytest.TempPathFactory) -> dict:
    toy, out = rapsf_toy, {}
    for kind, opts in (("acceptable", ACCEPTABLE), ("exact", {})):
        tg = Target("casadi", "ipopt", opts, retries=(), name=f"ipopt-{kind}")
        py = RAPSF(toy.sys, toy.X0, toy.F, toy.G, toy.W, toy.K, N, toy.Theta0, target=tg)
        d = tmp_path_factory.mktemp(f"rapsf_ipopt_{kind}")
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(E, "STATUS_OPTIONS", {**STATUS_OPTIONS, "ipopt": {"error_on_fail": True}})
            em = emit_rapsf(py, f"ri{kind[0]}", d)
        lib = build(d, em.name, werror=True, extra_flags=link_flags(em.libraries))
        out[kind] = (py, CRAPSF(lib, host=py))
    return out


@pytest.mark.parametrize("kind", ["acceptable", "exact"])
def test_c_uses_only_an_optimal_solve_as_python(pairs: dict, kind: str) -> None:
    """Along a short loop from states inside X: the same input (1e-6), fallback, status and
    uncertified words per step; at the acceptable stop ``optimal_inaccurate`` and the backup
    (no plan was ever stored), when IPOPT converges ``ok``."""
    py, c = pairs[kind]
    py.reset()
    c.reset()
    x, seen = np.array([0.3, -0.2]), set()
    for k in range(6):
        u_p = np.array([0.5 * np.sin(k)])
        (u1, i1), (u2, i2) = py.step(x, u_p), c.step(x, u_p)
        assert np.max(np.abs(u1 - u2)) <= 1e-6, (kind, k, u1, u2, i1.status, i2.status)
        assert (i1.status, i1.fallback, i1.uncertified) == \
            (i2.status, i2.fallback, i2.uncertified), (kind, k, i1, i2)
        seen.add((i1.status, i1.fallback))
        x = np.asarray(py.system.step(x, u1, np.array([1.2, 0.3])),
                       dtype=float).reshape(-1)
    want = {"acceptable": {("optimal_inaccurate", "backup")}, "exact": {("ok", None)}}[kind]
    assert seen == want, (kind, seen)
