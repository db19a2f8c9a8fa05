"""Every emitted attempt runs with the options its Python attempt runs with (session 14,
issue #14 "C = Python" by construction): the compiled problem's own for its first solver and
same-plugin retries, ``CasadiCompiled._retry_options`` for a retry on another plugin, plus
only what the C needs to read the verdict (``error_on_fail``). Before, the C added
IPOPT's ``acceptable_iter`` 0 to every IPOPT attempt, so the presets that start with IPOPT
(``exact``, ``long-horizon``, ``sampling-*``) ran other options in C than in Python; the
as-emitted targets' IPOPT retries keep it in both."""

from __future__ import annotations

import pytest

from balustrade.backends import compile
from balustrade.backends.emittable import STATUS_OPTIONS
from balustrade.codegen.emit import _Problem
from balustrade.examples.codegen import pendulum_pcbf_filter

ACCEPT_ITER = "ipopt.acceptable_iter"


def _python_options(c, k: int) -> dict:
    """The options the backend builds attempt ``k`` with (0: the first solver)."""
    if k == 0:
        return dict(c.options)
    name, over = c.retries[k - 1]
    return {**c.options, **over} if name == c.solver_name else c._retry_options(name, over)


@pytest.mark.parametrize("preset", ["exact", "long-horizon", "sampling-cold", "sampling-warm",
                                    "robust-sqp", "fast-sqp"])
def test_c_attempts_use_the_python_attempts_options(preset: str) -> None:
    ocp = pendulum_pcbf_filter().slack.ocp
    c = compile(ocp, preset)
    P = _Problem(c, "t_slack", "(2.24)", "t", None, True)
    got = P.nlpsol_options()
    emitted = [k for k, j in enumerate(P.c_attempt) if j is not None]
    assert len(got) == len(emitted)
    for (sym, plugin, opts), k in zip(got, emitted):
        verdict = {"error_on_fail": True} if plugin in STATUS_OPTIONS else {}
        assert opts == {**_python_options(c, k), **verdict}, (preset, sym, k)
    ipopt = [opts for _, plugin, opts in got if plugin == "ipopt"]
    assert ipopt, preset
    if c.solver_name == "ipopt":  # IPOPT first: its acceptable stop as in Python
        assert not c.as_emitted and ACCEPT_ITER not in ipopt[0], (preset, ipopt[0])
    else:                         # an as-emitted target's IPOPT retry: stopped alike
        assert c.as_emitted and all(o[ACCEPT_ITER] == 0 for o in ipopt), preset
