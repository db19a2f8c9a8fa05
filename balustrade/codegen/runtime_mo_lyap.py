"""Load the emitted Algorithm 6.3 step (:mod:`~balustrade.codegen.emit_mo_lyap`) with ctypes:
:class:`CMultiobjectiveLyapunovController`, the same ``step(x, u_p) -> (u, StepInfo)``,
``reset()``, status words, recorded values and fallbacks as
:class:`~balustrade.control.multiobjective.MultiobjectiveLyapunovController`, one foreign
call per step."""

from __future__ import annotations

import ctypes
import time
from pathlib import Path

import numpy as np

from balustrade._checks import as_vector
from balustrade.codegen import status as S
from balustrade.codegen.runtime import _PY_STATUS, _CProblemView, _dbl_p, _OwnsWork, _proposal, _ptr
from balustrade.codegen.runtime_robust import _refused
from balustrade.control.base import StepInfo
from balustrade.control.fallbacks import note_proposal

_CODES = S.by_code(S.MO_LYAP)


def mo_lyapunov_info(code: int, s_code: int, p_code: int, values: np.ndarray) -> StepInfo:
    """The :class:`StepInfo` of
    :class:`~balustrade.control.multiobjective.MultiobjectiveLyapunovController` for the
    same decisions: ``status`` (``"ok"``, ``"problem_<s>"``, ``"init_<s>"``,
    ``"non_finite_state"``), ``fallback``, ``values`` ``switch``, ``V_bound``, ``V``."""
    known, info = _refused(_CODES, code)
    if known is None:
        return info
    if known.name == "init_failed":
        info.status = f"init_{_PY_STATUS.get(s_code, str(s_code))}"
        return info
    info.values.update(switch=float(values[0]), V_bound=float(values[1]), V=float(values[2]))
    info.status = "ok" if known.name == "ok" else \
        f"problem_{_PY_STATUS.get(p_code, str(p_code))}"
    return info


class CMultiobjectiveLyapunovController(_OwnsWork):
    """The emitted Algorithm 6.3 step ((6.3) on the first step, then (6.10) with the
    switching rule (6.6)/(6.7)) as a closed-loop controller (everything computed in C)."""

    _BAD = S.code_of(S.MO_LYAP, "bad_input")

    def __init__(self, lib_path: str | Path, manifest: dict | None = None):
        m = self._open(lib_path, manifest, "mo_lyapunov",
                       "multiobjective Lyapunov controller (Algorithm 6.3)")
        Q = m["name"]
        self.nx, self.nu, self.N = m["nx"], m["nu"], m["N"]
        vp, ci = ctypes.c_void_p, ctypes.c_int
        self._step = self._lib.fn(f"{Q}_step", ci,
                                  [_dbl_p, _dbl_p, _dbl_p, ctypes.POINTER(ci), vp])
        self._status_fn = self._lib.fn(f"{Q}_solve_status", ci, [vp, ci])
        self._values_fn = self._lib.fn(f"{Q}_values", None, [vp, _dbl_p])
        self._replaced = self._lib.fn(f"{Q}_proposal_replaced", ci, [vp])
        self._allocate(Q)
        self.init = _CProblemView(self._lib, f"{Q}_first", m["problems"]["init"],
                                  self._lib.fn(f"{Q}_init_problem", vp, [vp])(self._work))
        self.problem = _CProblemView(self._lib, f"{Q}_problem", m["problems"]["problem"],
                                     self._lib.fn(f"{Q}_main_problem", vp, [vp])(self._work))
        self._x, self._u_p, self._u = np.zeros(self.nx), np.zeros(self.nu), np.zeros(self.nu)
        self._values = np.zeros(3)
        self._status = ci(0)
        self._args = (_ptr(self._x), _ptr(self._u_p), _ptr(self._u),
                      ctypes.byref(self._status), self._work)

    def reset(self) -> None:
        self._reset(self._work)

    def step_raw(self, x: np.ndarray, u_p: np.ndarray) -> tuple[np.ndarray, int]:
        """One C step without a StepInfo: ``(u, status code)`` (``u`` is a view)."""
        self._x[:] = x
        self._u_p[:] = u_p
        code = self._step(*self._args)
        return self._u, code

    def step(self, x: np.ndarray, u_p: np.ndarray) -> tuple[np.ndarray, StepInfo]:
        """One C step, reported as the Python controller reports it
        (:func:`mo_lyapunov_info`). Wrong shapes raise
        :class:`~balustrade.errors.ShapeError`; a NaN or inf ``x`` gives the projected
        proposal (``"non_finite_state"``); NaN or inf entries of ``u_p`` are read as 0
        (``"non_finite_proposal[_<status>]"``)."""
        u_p = _proposal(u_p, self.nu, "CMultiobjectiveLyapunovController.step: u_p")
        x = as_vector(x, "CMultiobjectiveLyapunovController.step: x", self.nx, finite=False)
        start = time.perf_counter()
        u, code = self.step_raw(x, u_p)
        elapsed = time.perf_counter() - start
        self._values_fn(self._work, _ptr(self._values))
        info = mo_lyapunov_info(code, self._status_fn(self._work, 0),
                                self._status_fn(self._work, 1), self._values)
        info.solve_time = elapsed
        if code != self._BAD:
            note_proposal(info, int(self._replaced(self._work)))
        return u.copy(), info


__all__ = ["CMultiobjectiveLyapunovController", "mo_lyapunov_info"]
