"""Load the emitted Algorithm 5.2 and 6.4 steps (:mod:`~balustrade.codegen.emit_robust`)
with ctypes: :class:`CRobustPCBFSafetyFilter` and :class:`CMultiobjectivePCBFFilter`, the
same ``step(x, u_p) -> (u, StepInfo)``, ``reset()``, status words and fallbacks as
:class:`~balustrade.control.robust.RobustPCBFSafetyFilter` and
:class:`~balustrade.control.multiobjective.MultiobjectivePCBFController`, one foreign call
per step."""

from __future__ import annotations

import ctypes
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from balustrade._checks import as_vector
from balustrade.codegen import status as S
from balustrade.codegen.runtime import (
    _OK,
    _PY_STATUS,
    _TRUNCATED,
    INACCURATE,
    _CProblemView,
    _dbl_p,
    _OwnsWork,
    _proposal,
    _ptr,
    py_status,
)
from balustrade.control.base import StepInfo
from balustrade.control.fallbacks import note_proposal

_ROBUST_CODES = S.by_code(S.ROBUST)
_MULTIOBJ_CODES = S.by_code(S.MULTIOBJ)


def _refused(family: dict[int, S.Status], code: int) -> tuple[S.Status | None, StepInfo]:
    """The :class:`StepInfo` every step starts from: an unknown code is status ``str(code)``
    with fallback ``"unknown"``, the family's ``bad_input`` is ``"non_finite_state"``
    (returned with the Status ``None``: nothing more to record); else the Status and a
    StepInfo with its fallback."""
    known = family.get(code)
    if known is None:
        return None, StepInfo(status=str(code), fallback="unknown")
    if known.name == "bad_input":
        return None, StepInfo(status="non_finite_state", fallback=known.fallback)
    return known, StepInfo(fallback=known.fallback)


def robust_info(code: int, s_code: int, f_code: int, h_r: float, h_cand: float,
                h_r_upper: float = float("nan"), s_inaccurate: bool = False,
                f_inaccurate: bool = False) -> StepInfo:
    """The :class:`StepInfo` :class:`~balustrade.control.robust.RobustPCBFSafetyFilter`
    records for the same decisions: ``status`` (``"ok"``, ``"slack_<s>"``,
    ``"filter_<f>"``, ``"non_finite_state"``; a converged C solve is named ``optimal``, one
    stopped by its budget ``truncated``), ``fallback``, ``values["h_r"]`` (after a
    converged (5.15)), ``values["h_r_upper"]`` (the cost of a feasible truncated (5.15):
    ``h_r_upper`` when finite), ``values["h_cand"]`` (when a candidate existed) and
    ``uncertified["filter"]`` (a feasible truncated (5.16), applied). ``s_inaccurate`` /
    ``f_inaccurate``: the (5.15) / (5.16) solve's ``BAL_OK`` stopped at the solver's
    acceptable level (``<P>_inaccurate``): ``uncertified["slack"]`` /
    ``uncertified["filter"]`` ``"optimal_inaccurate"`` and the status joined from them, as
    robust.py's ``note_solve`` records them."""
    known, info = _refused(_ROBUST_CODES, code)
    if known is None:
        return info
    if np.isfinite(h_cand):
        info.values["h_cand"] = h_cand
    if known.name == "above_candidate":  # robust.py: a failed (5.15), its value kept apart
        info.status, info.values["h_r_local"] = "slack_above_candidate", h_r
        return info
    if known.name in ("candidate", "projected_proposal"):
        info.status = f"slack_{_PY_STATUS.get(s_code, str(s_code))}"
        if np.isfinite(h_r_upper):
            info.values["h_r_upper"] = h_r_upper
        return info
    info.values["h_r"] = h_r
    if s_inaccurate and s_code == _OK:  # robust.py: note_solve(info, "slack", ...)
        info.uncertified["slack"] = INACCURATE
    if known.name != "ok":
        info.status = f"filter_{_PY_STATUS.get(f_code, str(f_code))}"
        return info
    if f_code == _TRUNCATED or (f_inaccurate and f_code == _OK):
        info.uncertified["filter"] = py_status(f_code, f_inaccurate)
    info.status = "ok" if not info.uncertified else "_".join(
        f"{k}_{v}" for k, v in info.uncertified.items())
    return info


class CRobustPCBFSafetyFilter(_OwnsWork):
    """The emitted Algorithm 5.2 step (5.15)+(5.16) as a closed-loop controller (the
    fallbacks computed in C). ``info.values["candidate_exact"] = 0`` marks a step whose
    new candidate the C had to drop (:mod:`~balustrade.codegen.emit_robust`)."""

    def __init__(self, lib_path: str | Path, manifest: dict | None = None,
                 keep_solutions: bool = False):
        m = self._open(lib_path, manifest, "robust", "robust PCBF filter")
        Q = m["name"]
        self.nx, self.nu, self.N = m["nx"], m["nu"], m["N"]
        self.keep_solutions = keep_solutions
        vp, ci = ctypes.c_void_p, ctypes.c_int
        self._step = self._lib.fn(f"{Q}_step", ci,
                                  [_dbl_p, _dbl_p, _dbl_p, _dbl_p, ctypes.POINTER(ci), vp])
        self._status_fn = self._lib.fn(f"{Q}_solve_status", ci, [vp, ci])
        self._h_cand = self._lib.fn(f"{Q}_h_cand", ctypes.c_double, [vp])
        self._replaced = self._lib.fn(f"{Q}_proposal_replaced", ci, [vp])
        self._exact = self._lib.fn(f"{Q}_candidate_exact", ci, [vp])
        self._allocate(Q)
        self.slack = _CProblemView(self._lib, f"{Q}_slack", m["problems"]["slack"],
                                   self._lib.fn(f"{Q}_slack_problem", vp, [vp])(self._work))
        self.filter = _CProblemView(self._lib, f"{Q}_filter", m["problems"]["filter"],
                                    self._lib.fn(f"{Q}_filter_problem", vp, [vp])(self._work))
        self._step_buffers()

    def reset(self) -> None:
        self._reset(self._work)

    _BAD = S.code_of(S.ROBUST, "bad_input")

    def step_raw(self, x: np.ndarray, u_p: np.ndarray) -> tuple[np.ndarray, float, int]:
        """One C step without a StepInfo: ``(u, h_r, status code)`` (``u`` is a view of
        the output buffer)."""
        self._x[:] = x
        self._u_p[:] = u_p
        code = self._step(*self._args)
        return self._u, float(self._h[0]), code

    def step(self, x: np.ndarray, u_p: np.ndarray) -> tuple[np.ndarray, StepInfo]:
        """One C step, reported as :class:`~balustrade.control.robust.
        RobustPCBFSafetyFilter` reports it (:func:`robust_info`). Wrong shapes raise
        :class:`~balustrade.errors.ShapeError`; a NaN or inf ``x`` gives the projected
        proposal (``"non_finite_state"``); NaN or inf entries of ``u_p`` are read as 0
        (``"non_finite_proposal[_<status>]"``)."""
        u_p = _proposal(u_p, self.nu, "CRobustPCBFSafetyFilter.step: u_p")
        x = as_vector(x, "CRobustPCBFSafetyFilter.step: x", self.nx, finite=False)
        start = time.perf_counter()
        u, h_r, code = self.step_raw(x, u_p)
        elapsed = time.perf_counter() - start
        s_code = self._status_fn(self._work, 0)
        # a feasible truncated (5.15) bounds h_r from above (robust.py's h_r_upper)
        h_r_upper = max(float(self.slack.value_fn(self.slack.work)), 0.0) \
            if s_code == _TRUNCATED and self.slack.truncated_feasible() else float("nan")
        f_code = self._status_fn(self._work, 1)
        info = robust_info(code, s_code, f_code, h_r, float(self._h_cand(self._work)),
                           h_r_upper, s_code == _OK and self.slack.inaccurate(),
                           f_code == _OK and self.filter.inaccurate())
        info.solve_time = elapsed
        if code != self._BAD:
            note_proposal(info, int(self._replaced(self._work)))
            if not self._exact(self._work):
                info.values["candidate_exact"] = 0.0
        if self.keep_solutions:
            info.solutions = {"slack": self.slack.unpack(self.slack.x.copy()),
                              "filter": self.filter.unpack(self.filter.x.copy())}
        return u.copy(), info


def multiobjective_info(code: int, s_code: int, p_code: int, values: np.ndarray,
                        s_inaccurate: bool = False, p_inaccurate: bool = False
                        ) -> StepInfo:
    """The :class:`StepInfo` of
    :class:`~balustrade.control.multiobjective.MultiobjectivePCBFController` for the same
    decisions: ``status`` (``"ok"``, ``"problem_<s>"``, ``"problem_above_bound"``, ``"init_<s>"``,
    ``"non_finite_state"``), ``fallback``, ``values`` ``h_cand``, ``bound``, ``h_tilde`` and,
    for ``"problem_above_bound"``, ``h_tilde_rejected`` (``values[3]``). ``s_inaccurate`` /
    ``p_inaccurate``: the (5.15) / (6.15) solve's ``BAL_OK`` stopped at the solver's
    acceptable level: ``uncertified["slack"]`` / ``uncertified["problem"]``
    ``"optimal_inaccurate"`` where multiobjective.py's ``note_solve`` records them (the
    status stays ``"ok"``, as there)."""
    known, info = _refused(_MULTIOBJ_CODES, code)
    if known is None:
        return info
    if known.name == "init_failed":
        info.status = f"init_{_PY_STATUS.get(s_code, str(s_code))}"
        return info
    if s_inaccurate and s_code == _OK:  # the initializing (5.15), used
        info.uncertified["slack"] = INACCURATE
    info.values.update(h_cand=float(values[0]), bound=float(values[1]),
                       h_tilde=float(values[2]))
    if known.name == "above_bound":   # multiobjective.py: a converged (6.15) above (6.15g)
        info.status = "problem_above_bound"
        info.values["h_tilde_rejected"] = float(values[3])
        return info
    if known.name == "ok" and p_inaccurate and p_code == _OK:
        info.uncertified["problem"] = INACCURATE
    info.status = "ok" if known.name == "ok" else \
        f"problem_{_PY_STATUS.get(p_code, str(p_code))}"
    return info


class _TwoProblemStep(_OwnsWork):
    """The ctypes plumbing shared by the emitted steps over two problems whose first one
    runs once or as a fallback (Algorithm 6.4: (5.15) then (6.15); Algorithm 6.3: (6.3) then
    (6.10)): ``<Q>_step(x, u_p, u_out, &status, work)``, the two solve statuses,
    :attr:`_N_VALUES` recorded values, the replaced-proposal flag and a view of each
    problem. Subclasses set :attr:`_LABEL` (error messages), :attr:`_BAD`, :attr:`_INFO` (a
    static function: codes and values → StepInfo) and may add to a StepInfo in
    :meth:`_annotate`."""

    _LABEL = "two-problem step"
    _BAD = -1
    #: how many doubles ``<Q>_values`` writes
    _N_VALUES = 3
    _INFO: Callable[[int, int, int, np.ndarray], StepInfo]

    def _load(self, lib_path: str | Path, manifest: dict | None, kind: str, what: str,
              first: tuple[str, str, str, str]) -> str:
        """Open the library; ``first`` = (attribute, C prefix suffix, manifest key, getter
        suffix) of the first problem's view. Returns the C prefix ``Q``."""
        m = self._open(lib_path, manifest, kind, what)
        Q = m["name"]
        self.nx, self.nu, self.N = m["nx"], m["nu"], m["N"]
        vp, ci = ctypes.c_void_p, ctypes.c_int
        self._step = self._lib.fn(f"{Q}_step", ci,
                                  [_dbl_p, _dbl_p, _dbl_p, ctypes.POINTER(ci), vp])
        self._status_fn = self._lib.fn(f"{Q}_solve_status", ci, [vp, ci])
        self._values_fn = self._lib.fn(f"{Q}_values", None, [vp, _dbl_p])
        self._replaced = self._lib.fn(f"{Q}_proposal_replaced", ci, [vp])
        self._allocate(Q)
        attr, suffix, key, getter = first
        self._FIRST = attr
        setattr(self, attr, _CProblemView(self._lib, f"{Q}_{suffix}", m["problems"][key],
                                          self._lib.fn(f"{Q}_{getter}", vp, [vp])(self._work)))
        self.problem = _CProblemView(self._lib, f"{Q}_problem", m["problems"]["problem"],
                                     self._lib.fn(f"{Q}_main_problem", vp, [vp])(self._work))
        self._x, self._u_p, self._u = np.zeros(self.nx), np.zeros(self.nu), np.zeros(self.nu)
        self._values = np.zeros(self._N_VALUES)
        self._status = ci(0)
        self._args = (_ptr(self._x), _ptr(self._u_p), _ptr(self._u),
                      ctypes.byref(self._status), self._work)
        return Q

    def reset(self) -> None:
        self._reset(self._work)

    def step_raw(self, x: np.ndarray, u_p: np.ndarray) -> tuple[np.ndarray, int]:
        """One C step without a StepInfo: ``(u, status code)`` (``u`` is a view)."""
        self._x[:] = x
        self._u_p[:] = u_p
        code = self._step(*self._args)
        return self._u, code

    def _annotate(self, info: StepInfo) -> None:
        """Additions to the StepInfo of a step that read its input (none by default)."""

    def step(self, x: np.ndarray, u_p: np.ndarray) -> tuple[np.ndarray, StepInfo]:
        """One C step, reported as the Python controller reports it. Wrong shapes raise
        :class:`~balustrade.errors.ShapeError`; a NaN or inf ``x`` gives the projected
        proposal (``"non_finite_state"``); NaN or inf entries of ``u_p`` are read as 0
        (``"non_finite_proposal[_<status>]"``)."""
        u_p = _proposal(u_p, self.nu, f"{self._LABEL}.step: u_p")
        x = as_vector(x, f"{self._LABEL}.step: x", self.nx, finite=False)
        start = time.perf_counter()
        u, code = self.step_raw(x, u_p)
        elapsed = time.perf_counter() - start
        self._values_fn(self._work, _ptr(self._values))
        s_code, p_code = self._status_fn(self._work, 0), self._status_fn(self._work, 1)
        first = getattr(self, self._FIRST)
        info = self._INFO(code, s_code, p_code, self._values,
                          s_code == _OK and first.inaccurate(),
                          p_code == _OK and self.problem.inaccurate())
        info.solve_time = elapsed
        if code != self._BAD:
            note_proposal(info, int(self._replaced(self._work)))
            self._annotate(info)
        return u.copy(), info


class CMultiobjectivePCBFFilter(_TwoProblemStep):
    """The emitted Algorithm 6.4 step ((5.15) once, then (6.15)) as a closed-loop
    controller (fallbacks computed in C); ``values["candidate_exact"] = 0`` as in
    :class:`CRobustPCBFSafetyFilter`."""

    _LABEL = "CMultiobjectivePCBFFilter"
    _BAD = S.code_of(S.MULTIOBJ, "bad_input")
    _INFO = staticmethod(multiobjective_info)
    _N_VALUES = 4   # h_cand, bound, h_tilde, h_tilde_rejected (bal/multiobj.h)

    def __init__(self, lib_path: str | Path, manifest: dict | None = None):
        Q = self._load(lib_path, manifest, "multiobjective", "multiobjective PCBF controller",
                       ("slack", "slack", "slack", "slack_problem"))
        self._exact = self._lib.fn(f"{Q}_candidate_exact", ctypes.c_int, [ctypes.c_void_p])

    def _annotate(self, info: StepInfo) -> None:
        if not self._exact(self._work):
            info.values["candidate_exact"] = 0.0


__all__ = ["CMultiobjectivePCBFFilter", "CRobustPCBFSafetyFilter", "multiobjective_info",
           "robust_info"]
