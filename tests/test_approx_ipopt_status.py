"""Algorithm 7.5 reports IPOPT's acceptable stop of (7.5) alike in Python and in its C
(session 14; the flag ``<P>_inaccurate`` of session 13, tests/test_ipopt_status.py).

:class:`~balustrade.control.approximate.ApproximatePCBFFilter` applies a (7.5) that ended
``optimal_inaccurate`` and flags it (``"filter_optimal_inaccurate"``, ``uncertified``). Its
fast path (:class:`~balustrade.backends.casadi_fast.FastNLP`, ``error_on_fail``) took IPOPT's
``Solved_To_Acceptable_Level`` for a converged solve and said ``"ok"``, and so did the C
(``BAL_OK``). Now the fast path hands such a stop to the compiled problem, which names it,
and :class:`~balustrade.codegen.CApproximatePCBFFilter` reads ``<name>_inaccurate``.

The pendulum with the terminal CBF as ``ĥ`` (ρ = 1/2, as tests/test_codegen_approximate.py),
(7.6) and (7.5) on IPOPT alone with a tolerance it cannot meet and one acceptable iterate
enough (the emitted C keeps those options, as tests/test_ipopt_status.py does), and on
IPOPT converging."""

from __future__ import annotations

import numpy as np
import pytest
from test_ipopt_status import ACCEPTABLE

from balustrade.backends.emittable import STATUS_OPTIONS
from balustrade.backends.targets import Target
from balustrade.codegen import CApproximatePCBFFilter, build, emit_approximate
from balustrade.codegen import emit as E
from balustrade.control.approximate import ApproximatePCBFFilter
from balustrade.design.terminal_cbf import synthesize_terminal_cbf
from balustrade.models.pendulum import pendulum, pendulum_setup


@pytest.fixture(scope="module")
def pairs(tmp_path_factory: pytest.TempPathFactory) -> dict:
    system, s = pendulum(), pendulum_setup()
    h = synthesize_terminal_cbf(system.A, system.B, s.X, s.U, delta_N=s.deltas[-1])
    out, flags = {}, E._link_flags(("ipopt",))
    for kind, opts in (("acceptable", ACCEPTABLE), ("exact", {})):
        tg = Target("casadi", "ipopt", opts, retries=(), name=f"ipopt-{kind}")
        py = ApproximatePCBFFilter(system, s.U, h, rho=0.5, target=tg)
        d = tmp_path_factory.mktemp(f"approx_ipopt_{kind}")
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(E, "STATUS_OPTIONS", {**STATUS_OPTIONS, "ipopt": {"error_on_fail": True}})
            em = emit_approximate(py, f"ai{kind[0]}", d, dynamics=system.function,
                                  allow_external=True)
        out[kind] = (py, CApproximatePCBFFilter(build(d, em.name, werror=True,
                                                      extra_flags=flags)))
    return out


@pytest.mark.parametrize("kind", ["acceptable", "exact"])
def test_filter_status_words_equal_in_c_and_python(pairs: dict, kind: str) -> None:
    """On random states and proposals: the same status, fallback and uncertified words and
    inputs (1e-6); the (7.5) solves that ran are ``filter_optimal_inaccurate`` at the
    acceptable stop and ``ok`` when IPOPT converged."""
    py, c = pairs[kind]
    py.reset()
    c.reset()
    rng = np.random.default_rng(3)
    seen = set()
    for x, u_p in zip(rng.uniform([-0.7, -2.0], [0.7, 2.0], (30, 2)),
                      rng.uniform(-4, 4, (30, 1))):
        (u1, i1), (u2, i2) = py.step(x, u_p), c.step(x, u_p)
        assert (i1.status, i1.fallback, i1.uncertified) == \
            (i2.status, i2.fallback, i2.uncertified), (kind, x, u_p, i1, i2)
        assert np.max(np.abs(u1 - u2)) <= 1e-6, (kind, x, u1, u2)
        seen.add(i1.status)
    filtered = {"acceptable": "filter_optimal_inaccurate", "exact": "ok"}[kind]
    assert filtered in seen and "filter_optimal_inaccurate" not in seen - {filtered}, seen
