"""Load the emitted Algorithm 6.3 step (:mod:`~balustrade.codegen.emit_mo_lyap`) with ctypes:
:class:`CMultiobjectiveLyapunovController`, the same ``step(x, u_p) -> (u, StepInfo)``,
``reset()``, status words, recorded values and fallbacks as
:class:`~balustrade.control.multiobjective.MultiobjectiveLyapunovController`, one foreign
call per step."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from balustrade.codegen import status as S
from balustrade.codegen.runtime import _OK, _PY_STATUS, INACCURATE
from balustrade.codegen.runtime_robust import _refused, _TwoProblemStep
from balustrade.control.base import StepInfo

_CODES = S.by_code(S.MO_LYAP)


def mo_lyapunov_info(code: int, s_code: int, p_code: int, values: np.ndarray,
                     s_inaccurate: bool = False, p_inaccurate: bool = False) -> StepInfo:
    """The :class:`StepInfo` of
    :class:`~balustrade.control.multiobjective.MultiobjectiveLyapunovController` for the
    same decisions: ``status`` (``"ok"``, ``"problem_<s>"``, ``"init_<s>"``,
    ``"non_finite_state"``), ``fallback``, ``values`` ``switch``, ``V_bound``, ``V``;
    ``uncertified["init"]`` / ``["problem"]`` ``"optimal_inaccurate"`` for a (6.3) / (6.10)
    whose ``BAL_OK`` stopped at the solver's acceptable level (``s_inaccurate`` /
    ``p_inaccurate``), as the Python controller's ``note_solve``."""
    known, info = _refused(_CODES, code)
    if known is None:
        return info
    if known.name == "init_failed":
        info.status = f"init_{_PY_STATUS.get(s_code, str(s_code))}"
        return info
    if s_inaccurate and s_code == _OK:
        info.uncertified["init"] = INACCURATE
    info.values.update(switch=float(values[0]), V_bound=float(values[1]), V=float(values[2]))
    if known.name == "ok" and p_inaccurate and p_code == _OK:
        info.uncertified["problem"] = INACCURATE
    info.status = "ok" if known.name == "ok" else \
        f"problem_{_PY_STATUS.get(p_code, str(p_code))}"
    return info


class CMultiobjectiveLyapunovController(_TwoProblemStep):
    """The emitted Algorithm 6.3 step ((6.3) on the first step, then (6.10) with the
    switching rule (6.6)/(6.7)) as a closed-loop controller (everything computed in C);
    reported as :func:`mo_lyapunov_info` says."""

    _LABEL = "CMultiobjectiveLyapunovController"
    _BAD = S.code_of(S.MO_LYAP, "bad_input")
    _INFO = staticmethod(mo_lyapunov_info)

    def __init__(self, lib_path: str | Path, manifest: dict | None = None):
        self._load(lib_path, manifest, "mo_lyapunov",
                   "multiobjective Lyapunov controller (Algorithm 6.3)",
                   ("init", "first", "init", "init_problem"))


__all__ = ["CMultiobjectiveLyapunovController", "mo_lyapunov_info"]
