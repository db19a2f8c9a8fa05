"""Load the emitted Algorithm 4.1 step (:mod:`~balustrade.codegen.emit_rapsf`) with ctypes:
:class:`CRAPSF`, the same ``step(x, u_p) -> (u, StepInfo)``, ``reset()``, status words and
fallbacks as :class:`~balustrade.control.rapsf.RAPSF`, one foreign call per step.

The parameter set ``Θ_k`` is not computed in C: :class:`CRAPSF` keeps a copy of the Python
controller (``host``) whose estimator update (line 4 of Algorithm 4.1, the nesting check of
Assumption 4.2, the ``"model_falsified"`` rule) and constants ``s_jr`` it runs before each
C step, and passes the vertices (padded by repetition, as the Python controller pads them)
and ``s`` to the C. With the Remark 4.6 variant emitted (``shrinking=True``) the C also
solves (4.5) with the horizon ``N − k_inf`` after a failure; its status is recorded as
the Python controller records it (``"shrunk_horizon"``, or ``uncertified["rapsf_shrunk"]``
when it failed too). A (4.5) whose solver stopped at its acceptable level (``BAL_OK`` with
``<name>_inaccurate`` 1) is not used by the C, as RAPSF uses only an ``optimal`` solve, and
is named ``optimal_inaccurate`` (tests/test_rapsf_acceptable_stop.py)."""

from __future__ import annotations

import copy
import ctypes
import time
from pathlib import Path

import numpy as np

from balustrade._checks import as_vector
from balustrade.codegen import status as S
from balustrade.codegen.runtime import (
    _OK,
    _CProblemView,
    _dbl_p,
    _OwnsWork,
    _proposal,
    _ptr,
    py_status,
)
from balustrade.control.base import StepInfo
from balustrade.errors import BalustradeError, CodegenError

_CODES = S.by_code(S.RAPSF)


def _host_copy(controller: object) -> object:
    """A copy of the RAPSF ``controller`` with its own estimator (deep copy), reset: the C
    controller's Θ_k evolves independently of the original's."""
    for attr in ("_update_theta", "vertices", "reset"):
        if not hasattr(controller, attr):
            raise CodegenError(f"CRAPSF: host must be the RAPSF controller that was emitted, "
                               f"got {type(controller).__name__}")
    host = copy.copy(controller)
    host.estimator = copy.deepcopy(controller.estimator)
    host.reset()
    return host


class CRAPSF(_OwnsWork):
    """The emitted Algorithm 4.1 step as a closed-loop controller (the fallbacks computed in
    C, ``Θ_k`` and ``s`` in Python on ``host``, a copy of the emitted
    :class:`~balustrade.control.rapsf.RAPSF`; :func:`~balustrade.codegen.accelerate`
    passes it). ``values``: ``k_inf``, ``n_vertices`` and ``objective`` (after a converged
    (4.5)), as the Python controller records them."""

    _BAD = S.code_of(S.RAPSF, "bad_input")
    _OK = S.code_of(S.RAPSF, "ok")
    _FALSIFIED = S.code_of(S.RAPSF, "model_falsified")
    _NOT_RUN = S.code_of(S.SOLVE, "not_run")

    def __init__(self, lib_path: str | Path, manifest: dict | None = None,
                 host: object | None = None):
        m = self._open(lib_path, manifest, "rapsf", "RAPSF (Algorithm 4.1)")
        host = host if host is not None else m.get("_host")
        if host is None:
            raise CodegenError("CRAPSF: pass host=<the emitted RAPSF controller>: its "
                               "estimator computes Θ_k for the C step")
        self.host = _host_copy(host)
        Q = m["name"]
        self.nx, self.nu, self.N = m["nx"], m["nu"], m["N"]
        self.nq, self.n_vertices, self.n_rows = m["nq"], m["n_vertices"], m["n_rows"]
        vp, ci = ctypes.c_void_p, ctypes.c_int
        self._step = self._lib.fn(f"{Q}_step", ci, [_dbl_p, _dbl_p, _dbl_p, _dbl_p, ci,
                                                    _dbl_p, ctypes.POINTER(ci), vp])
        self._status_fn = self._lib.fn(f"{Q}_solve_status", ci, [vp])
        self._shrunk_fn = self._lib.fn(f"{Q}_shrunk_status", ci, [vp])
        self.shrinking = bool(m.get("shrinking", False))
        self._k_inf = self._lib.fn(f"{Q}_k_inf", ci, [vp])
        self._objective = self._lib.fn(f"{Q}_objective", ctypes.c_double, [vp])
        # an attempt that can stop at its acceptable level: the C does not use
        # such a BAL_OK, as RAPSF does not use an optimal_inaccurate solve; its word
        self._inaccurate = self._lib.fn(f"{Q}_inaccurate", ci, [vp, ci]) if any(
            p.get("acceptable_stop", True) for p in m["problems"].values()) else None
        self._allocate(Q)
        #: ``"hot"``: (4.5) hot-started in C (bal/rapsf_hot.h, the default target's C);
        #: else the SQP of target "convex-qp" (bal/rapsf.h) with its problem view ``main``
        self.qp = m.get("qp", "sqp")
        self.main = None
        self._qp_info = None
        if self.qp == "hot":
            self._qp_info = self._lib.fn(f"{Q}_qp_info", None, [vp, _dbl_p])
            self._info_buf = np.zeros(6)
            self._qp_point = [self._lib.fn(f"{Q}_qp_{k}", ctypes.POINTER(ctypes.c_double),
                                           [vp]) for k in ("primal", "dual")]
            sizes = m.get("qp_sizes", {"all": m["qp_size"]})
            self.qp_sizes = [tuple(sizes["all"]), tuple(sizes.get("shared", sizes["all"]))]
        else:
            self.main = _CProblemView(self._lib, f"{Q}_main", m["problems"]["main"],
                                      self._lib.fn(f"{Q}_main_problem", vp, [vp])(self._work))
        self._x, self._u_p, self._u = np.zeros(self.nx), np.zeros(self.nu), np.zeros(self.nu)
        self._theta = np.zeros(self.nq * self.n_vertices)
        self._s = np.zeros(self.n_rows * self.n_vertices)
        self._status = ci(0)

    def qp_info(self) -> dict:
        """The last step's hot-started solve (``qp == "hot"`` only): the solver's ``flag``,
        the ``kkt`` residual, ``iterations``, whether it was ``retried`` cold, whether the
        values of ``A(p)`` changed (``a_changed``) and whether the QP with the shared rows
        was solved (``shared``)."""
        if self._qp_info is None:
            raise CodegenError("CRAPSF.qp_info: only for the hot-started QP (qp == 'hot')")
        self._qp_info(self._work, _ptr(self._info_buf))
        f, k, it, retried, changed, shared = self._info_buf
        return {"flag": int(f), "kkt": float(k), "iterations": int(it),
                "retried": bool(retried), "a_changed": bool(changed), "shared": bool(shared)}

    def qp_point(self) -> tuple[np.ndarray, np.ndarray]:
        """Copies of the last hot-started solve's point ``y`` and multipliers (``qp ==
        "hot"`` only; for checks against the Python lowering of (4.5))."""
        if self._qp_info is None:
            raise CodegenError("CRAPSF.qp_point: only for the hot-started QP (qp == 'hot')")
        m, n = self.qp_sizes[int(self.qp_info()["shared"])]
        y, z = (fn(self._work) for fn in self._qp_point)
        return np.ctypeslib.as_array(y, (n,)).copy(), np.ctypeslib.as_array(z, (m,)).copy()

    @property
    def k_inf(self) -> int:
        return int(self._k_inf(self._work))

    def reset(self) -> None:
        """A new closed loop: the C forgets its plan (``k_inf = N − 1``), the host goes back
        to ``Θ₀`` (its estimator's own ``reset`` included)."""
        self._reset(self._work)
        self.host.reset()

    def _vertex_data(self) -> None:
        """``theta`` and ``s`` of the host's ``Θ_k``, padded by repetition to the compiled
        number of vertex columns (column-major, as the problem stacks them)."""
        V, s = np.atleast_2d(self.host.vertices), self.host._s
        if len(V) > self.n_vertices:
            raise BalustradeError(f"CRAPSF.step: Θ_k has {len(V)} vertices, the C was "
                                  f"emitted for {self.n_vertices} (theta of shape "
                                  f"({self.nq}, {self.n_vertices})); emit it again")
        idx = np.arange(self.n_vertices) % len(V)
        self._theta[:] = V[idx].T.reshape(-1, order="F")
        self._s[:] = s[:, idx].reshape(-1, order="F")

    def _was_inaccurate(self, code: int, which: int) -> bool:
        """The solve (0: (4.5), 1: the shrunk horizon) returned ``BAL_OK`` at the solver's
        acceptable level (``<Q>_inaccurate``): ``optimal_inaccurate``, not used."""
        return code == _OK and self._inaccurate is not None and \
            bool(self._inaccurate(self._work, which))

    def step_raw(self, x: np.ndarray, u_p: np.ndarray, falsified: bool = False
                 ) -> tuple[np.ndarray, int]:
        """One C step with the vertex data already loaded: ``(u, status code)`` (``u`` is a
        view of the output buffer)."""
        self._x[:] = x
        self._u_p[:] = u_p
        code = self._step(_ptr(self._x), _ptr(self._u_p), _ptr(self._theta), _ptr(self._s),
                          int(bool(falsified)), _ptr(self._u), ctypes.byref(self._status),
                          self._work)
        return self._u, code

    def step(self, x: np.ndarray, u_p: np.ndarray) -> tuple[np.ndarray, StepInfo]:
        """One step: the host's Θ_k update, then one C call (module docstring). Wrong shapes
        raise :class:`~balustrade.errors.ShapeError`; a NaN or inf ``x`` gives the backup
        ``K x`` with NaN entries as 0 (``"non_finite_state"``); NaN or inf entries of
        ``u_p`` are read as 0 (``"non_finite_proposal"``)."""
        u_p = _proposal(u_p, self.nu, "CRAPSF.step: u_p")
        x = as_vector(x, "CRAPSF.step: x", self.nx, finite=False)
        h = self.host
        info = StepInfo()
        if not np.all(np.isfinite(u_p)):
            info.status = "non_finite_proposal"
        h._update_theta(x, info)
        info.values["n_vertices"] = float(len(h.vertices))
        self._vertex_data()
        start = time.perf_counter()
        u, code = self.step_raw(x, u_p, h.falsified)
        info.solve_time = time.perf_counter() - start
        known = _CODES.get(code)
        if known is None:
            info.status, info.fallback = str(code), "unknown"
        elif code == self._BAD:
            info.status, info.fallback = "non_finite_state", known.fallback
        elif code == self._FALSIFIED:
            info.status, info.fallback = "model_falsified", known.fallback
        elif code == self._OK:
            info.values["objective"] = float(self._objective(self._work))
        else:
            solve = self._status_fn(self._work)
            name = py_status(solve, self._was_inaccurate(solve, 0))
            info.uncertified["rapsf"] = name
            if info.status == "ok":
                info.status = name
            info.fallback = known.fallback
            shrunk = self._shrunk_fn(self._work)        # Remark 4.6's solve, if it ran
            if shrunk != self._NOT_RUN and known.name != "shrunk_horizon":
                info.uncertified["rapsf_shrunk"] = py_status(
                    shrunk, self._was_inaccurate(shrunk, 1))
        info.values["k_inf"] = float(self.k_inf)
        u = u.copy()
        h._prev = (x, u) if np.all(np.isfinite(x)) else None   # as RAPSF.step
        h.k += 1
        return u, info


__all__ = ["CRAPSF"]
