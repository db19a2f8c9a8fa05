"""Load the emitted Algorithm 8.7 (:func:`~balustrade.codegen.emit_grid.emit_grid`) with
ctypes: :class:`CGridPCBFFilter`, a closed-loop controller with the interface, statuses and
counters of :class:`~balustrade.control.approximate.GridPCBFFilter`, one foreign call per
step (all grid candidates are evaluated inside it). The step solves no optimization problem
(it evaluates ``ĥ(f(x, u_i))`` on the grid), so there is no solver status to read: no
``<P>_inaccurate``, no acceptable stop (unlike Algorithm 7.5,
:class:`~balustrade.codegen.CApproximatePCBFFilter`)."""

from __future__ import annotations

import ctypes
import time
from pathlib import Path

import numpy as np

from balustrade.codegen import status as S
from balustrade.codegen.runtime import _dbl_p, _load, _OwnsWork
from balustrade.control.base import StepInfo
from balustrade.control.fallbacks import note_proposal


class CGridPCBFFilter(_OwnsWork):
    """The emitted Algorithm 8.7 as a controller: ``step(x, u_p) -> (u, StepInfo)`` with
    ``status`` ``"ok"`` / ``"no_decreasing_candidate"`` (fallback ``"grid_minimizer"``) /
    ``"non_finite_state"`` (fallback ``"previous_input"``), ``values["h_hat"]`` and
    ``values["n_candidates"]``; ``reset()``; counters ``n_steps`` and
    ``n_decrease_infeasible``; ``u_prev`` (``u_{k−1}``, a copy)."""

    _CODES = S.by_code(S.GRID)
    _BAD = S.code_of(S.GRID, "non_finite_state")

    def __init__(self, lib_path: str | Path, manifest: dict | None = None):
        m = self._open(lib_path, manifest, "grid", "Algorithm 8.7 filter")
        A, vp = m["name"], ctypes.c_void_p
        self.nx, self.nu = m["nx"], m["nu"]
        self._step = self._lib.fn(f"{A}_step", ctypes.c_int,
                                  [_dbl_p, _dbl_p, _dbl_p, _dbl_p,
                                   ctypes.POINTER(ctypes.c_int), vp])
        self._n_cand = self._lib.fn(f"{A}_n_candidates", ctypes.c_int, [vp])
        self._counter = self._lib.fn(f"{A}_counter", ctypes.c_long, [vp, ctypes.c_int])
        self._replaced = self._lib.fn(f"{A}_proposal_replaced", ctypes.c_int, [vp])
        u_prev = self._lib.fn(f"{A}_u_prev", _dbl_p, [vp])
        self._allocate(A)
        self._u_prev = np.ctypeslib.as_array(u_prev(self._work), shape=(self.nu,))
        self._step_buffers()

    def reset(self) -> None:
        """``u_{k−1} := Π_U(u_init)``, counters to zero (as the Python filter)."""
        self._reset(self._work)

    @property
    def u_prev(self) -> np.ndarray:
        return self._u_prev.copy()

    @property
    def n_steps(self) -> int:
        return int(self._counter(self._work, 0))

    @property
    def n_decrease_infeasible(self) -> int:
        return int(self._counter(self._work, 1))

    def step(self, x: np.ndarray, u_p: np.ndarray) -> tuple[np.ndarray, StepInfo]:
        """One C step, reported as :class:`~balustrade.control.approximate.GridPCBFFilter`
        reports it. Wrong shapes raise :class:`~balustrade.errors.ShapeError`; NaN or inf
        never raise (a non-finite ``x`` keeps ``u_{k−1}``, non-finite entries of ``u_p``
        are read as 0: ``"non_finite_proposal[_<status>]"``)."""
        _load(self._u_p, u_p, "CGridPCBFFilter.step: u_p", proposal=True)
        _load(self._x, x, "CGridPCBFFilter.step: x")
        start = time.perf_counter()
        code = self._step(*self._args)
        elapsed = time.perf_counter() - start
        known = self._CODES.get(code)
        info = StepInfo(status=known.name if known is not None else str(code),
                        fallback=known.fallback if known is not None else "unknown",
                        solve_time=elapsed)
        if code == self._BAD:
            return self._u.copy(), info
        info.values.update(h_hat=float(self._h[0]),
                           n_candidates=float(self._n_cand(self._work)))
        return self._u.copy(), note_proposal(info, int(self._replaced(self._work)))


__all__ = ["CGridPCBFFilter"]
