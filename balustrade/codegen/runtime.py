"""Load emitted C with ctypes and call it from Python with preallocated buffers.

* :class:`CFunction` — a plain emitted function (``fn(arg, res, iw, w, mem)``);
* :class:`CProblem` — one emitted problem (``<name>_solve``), ``solve(params)``;
* :class:`CPCBFSafetyFilter` — the emitted PCBF step (2.24)+(2.23) as a
  :class:`~balustrade.control.base.Controller`, so :func:`~balustrade.control.simulate`
  runs the exact code that is deployed.

Each object holds its work struct (allocated by the library, freed on ``close()`` or
garbage collection) and numpy buffers whose addresses are passed once; a call copies
inputs in, makes one foreign call and reads outputs from the same buffers.
"""

from __future__ import annotations

import ctypes
import json
import math
import time
from pathlib import Path

import numpy as np

from balustrade._checks import as_vector
from balustrade.backends.emittable import c_retry_chain
from balustrade.backends.solution import FEASIBILITY_TOL
from balustrade.codegen import status as S
from balustrade.control.base import StepInfo
from balustrade.control.fallbacks import note_proposal
from balustrade.dsl.layout import Layout  # the stacking and checks of OCP.pack_parameters
from balustrade.errors import BalustradeError, CodegenError, ShapeError

_dbl_p = ctypes.POINTER(ctypes.c_double)
#: solve status code -> name (``balustrade.codegen.status.SOLVE``)
_STATUS = {code: st.name for code, st in S.by_code(S.SOLVE).items()}
_OK, _FEASIBLE = S.code_of(S.SOLVE, "ok"), S.code_of(S.SOLVE, "feasible")
_SOLVED = (_OK, _FEASIBLE)
_BAD_INPUT = S.code_of(S.SOLVE, "bad_input")
#: a solve stopped by its iteration budget (real-time mode): named "truncated", the word
#: the Python controllers record (``balustrade.control.base.TRUNCATED``)
_TRUNCATED = S.code_of(S.SOLVE, "truncated")
#: solve status code -> the Solution status of the Python backend where they coincide
#: (a converged C solve is the backend's "optimal"); the others keep the C name
_PY_STATUS = {**_STATUS, _OK: "optimal"}
#: the backend's name of a solve the C returned ``BAL_OK`` for with ``<P>_inaccurate`` 1 (the
#: solver stopped at its acceptable level: ``Status.OPTIMAL_INACCURATE``, used, never
#: certified optimal; bal/problem.h)
INACCURATE = "optimal_inaccurate"


def py_status(code: int, inaccurate: bool = False) -> str:
    """The backend's status name of a C solve status ``code`` (``_PY_STATUS``), with a
    ``BAL_OK`` that stopped at the solver's acceptable level (``inaccurate``) named
    :data:`INACCURATE`, as :class:`~balustrade.backends.casadi_backend.CasadiCompiled`
    names it."""
    return INACCURATE if code == _OK and inaccurate else _PY_STATUS.get(code, str(code))
#: PCBF step code -> Status (``balustrade.codegen.status.PCBF``), read once per step
_PCBF_CODES = S.by_code(S.PCBF)


def _proposal(u_p: object, nu: int, block: str) -> np.ndarray:
    """``u_p`` as a vector of ``nu`` entries for a C step (a single value is repeated; NaN and
    inf are kept: the C reads them as 0), else ShapeError naming ``block``."""
    u_p = np.asarray(u_p, dtype=float).reshape(-1)
    if u_p.size == 1 and nu > 1:  # np.broadcast_to costs ~5 us: only where it changes u_p
        u_p = np.full(nu, u_p[0])
    return as_vector(u_p, block, nu, finite=False)


_F64 = np.dtype(float)


def _load(buf: np.ndarray, value: object, block: str, proposal: bool = False) -> bool:
    """Copy a step input into its preallocated buffer ``buf``, checked as :func:`_proposal`
    (``proposal=True``: one value is repeated, NaN and inf kept) or ``as_vector(...,
    finite=False)`` do; a float, or a float64 array of the buffer's shape, skips the
    general checks (~2 µs per step: a fifth of a C step of the pendulum). Returns True
    when the fast path saw that every entry is finite (the C then replaced none: no call
    needed to ask), else False (unknown)."""
    kind = type(value)
    if kind is np.ndarray and value.dtype == _F64 and value.shape == buf.shape:
        buf[:] = value
        return proposal and buf.size <= 4 and all(map(math.isfinite, buf.tolist()))
    if (kind is float or kind is int) and (proposal or buf.size == 1):
        buf.fill(value)
        return math.isfinite(value)
    buf[:] = _proposal(value, buf.size, block) if proposal else \
        as_vector(value, block, buf.size, finite=False)
    return False


def _ptr(a: np.ndarray) -> ctypes._Pointer:
    return a.ctypes.data_as(_dbl_p)


def load_manifest(src_dir: str | Path, name: str | None = None) -> dict:
    """Read ``<name>.json`` written by the ``emit_*`` functions."""
    src_dir = Path(src_dir)
    path = src_dir / f"{name}.json" if name else next(iter(sorted(src_dir.glob("*.json"))),
                                                       None)
    if path is None or not path.is_file():
        raise CodegenError(f"no balustrade manifest (<name>.json) in {src_dir}")
    try:
        manifest = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CodegenError(f"{path}: not a readable balustrade manifest: {exc}") from exc
    if not isinstance(manifest, dict) or "kind" not in manifest:
        raise CodegenError(f"{path}: not a balustrade manifest (no 'kind')")
    return manifest


class _Library:
    """A loaded shared library and its manifest."""

    def __init__(self, lib_path: str | Path, manifest: dict | None = None):
        self.path = Path(lib_path)
        if not self.path.exists():
            raise CodegenError(f"shared library {self.path} not found (run build() first)")
        try:
            self.lib = ctypes.CDLL(str(self.path.resolve()))
        except OSError as exc:
            raise CodegenError(f"could not load {self.path}: {exc}") from exc
        self.manifest = manifest if manifest is not None else load_manifest(self.path.parent)

    def fn(self, sym: str, restype: object, argtypes: list) -> ctypes._CFuncPtr:
        try:
            f = getattr(self.lib, sym)
        except AttributeError as exc:
            raise CodegenError(f"{self.path.name}: symbol {sym!r} not found; was it emitted "
                               "with this name?") from exc
        f.restype, f.argtypes = restype, argtypes
        return f


    def raw(self, sym: str, restype: object) -> ctypes._CFuncPtr:
        """A second handle on ``sym`` without ``argtypes``: for hot calls whose arguments
        are all prebuilt ctypes objects of the right types (pointers, ``c_void_p``,
        ``c_int``), which ctypes then passes without converting or checking them (~0.3 µs
        per argument-checked call on this machine). The checked handle of :meth:`fn`
        is not changed."""
        try:
            f = self.lib[sym]  # item access: a new function object (attributes are cached)
        except AttributeError as exc:
            raise CodegenError(f"{self.path.name}: symbol {sym!r} not found; was it emitted "
                               "with this name?") from exc
        f.restype, f.argtypes = restype, None
        return f


class CFunction:
    """A plain emitted function called through ctypes: ``outs = f(*inputs)`` (dense
    column-major inputs; outputs are new arrays of the declared shapes, or views of the
    preallocated output buffers with ``copy=False``)."""

    def __init__(self, lib_path: str | Path, sym: str, manifest: dict | None = None):
        self._lib = _Library(lib_path, manifest)
        info = self._lib.manifest.get("functions", {}).get(sym)
        if info is None:
            raise CodegenError(f"{self._lib.path.name}: no emitted function {sym!r} (have "
                               f"{sorted(self._lib.manifest.get('functions', {}))})")
        self.sym = sym
        ll = ctypes.c_longlong
        work = self._lib.fn(f"{sym}_work", ctypes.c_int, [ctypes.POINTER(ll)] * 4)
        sizes = [ll(0) for _ in range(4)]
        work(*[ctypes.byref(s) for s in sizes])
        n_arg, n_res, n_iw, n_w = (max(int(s.value), 1) for s in sizes)
        self._in_shapes = [tuple(s) for s in info["in"]]
        self._out_shapes = [tuple(s) for s in info["out"]]
        self._inputs = [np.zeros(int(np.prod(s)) or 1) for s in self._in_shapes]
        self._outputs = [np.zeros(int(np.prod(s)) or 1) for s in self._out_shapes]
        self._in_sizes = [int(np.prod(s)) for s in self._in_shapes]
        self._out_views = [b[: int(np.prod(s))].reshape(s, order="F") for b, s in
                           zip(self._outputs, self._out_shapes)]
        self._arg = (_dbl_p * n_arg)(*[_ptr(a) for a in self._inputs])
        self._res = (_dbl_p * n_res)(*[_ptr(a) for a in self._outputs])
        self._iw = (ll * n_iw)()
        self._w = (ctypes.c_double * n_w)()
        self._f = self._lib.fn(sym, ctypes.c_int, [ctypes.c_void_p] * 4 + [ctypes.c_int])
        self._lib.fn(f"{sym}_incref", None, [])()
        self._release = self._lib.fn(f"{sym}_release", None, [ctypes.c_int])
        self._decref = self._lib.fn(f"{sym}_decref", None, [])
        self._mem = self._lib.fn(f"{sym}_checkout", ctypes.c_int, [])()
        if self._mem < 0:
            raise CodegenError(f"{sym}: no CasADi memory left (rebuild with a larger "
                               "-DCASADI_MAX_NUM_THREADS)")
        self._args = (ctypes.cast(self._arg, ctypes.c_void_p), ctypes.cast(self._res,
                      ctypes.c_void_p), ctypes.cast(self._iw, ctypes.c_void_p),
                      ctypes.cast(self._w, ctypes.c_void_p), self._mem)

    def __call__(self, *inputs: object, copy: bool = True) -> list[np.ndarray]:
        if len(inputs) != len(self._inputs):
            raise CodegenError(f"{self.sym}: expected {len(self._inputs)} inputs, got "
                               f"{len(inputs)}")
        for k, (buf, n, val, shape) in enumerate(zip(self._inputs, self._in_sizes, inputs,
                                                     self._in_shapes)):
            if n:
                try:
                    flat = np.ravel(np.asarray(val, dtype=float), order="F")
                except (TypeError, ValueError) as exc:
                    raise BalustradeError(f"{self.sym}: input {k} must be numbers of shape "
                                          f"{shape}, got {type(val).__name__}") from exc
                if flat.size != n:
                    raise ShapeError(f"{self.sym}: input {k}", shape, np.shape(val))
                buf[:n] = flat
        if self._f(*self._args):
            raise CodegenError(f"{self.sym}: evaluation failed")
        return [o.copy() for o in self._out_views] if copy else self._out_views

    def close(self) -> None:
        if getattr(self, "_mem", -1) >= 0:
            self._release(self._mem)
            self._decref()
            self._mem = -1

    def __del__(self) -> None:  # pragma: no cover - interpreter shutdown order
        try:
            self.close()
        except Exception:
            pass


class _CProblemView:
    """Numpy views of one problem's work struct inside the library (x, f, ...)."""

    def __init__(self, lib: _Library, prefix: str, info: dict, work_ptr: int):
        self.info = info
        primal = lib.fn(f"{prefix}_primal", _dbl_p, [ctypes.c_void_p])
        self.value_fn = lib.fn(f"{prefix}_value", ctypes.c_double, [ctypes.c_void_p])
        self.work = work_ptr
        self.x = np.ctypeslib.as_array(primal(work_ptr), shape=(info["nw"],))
        self._res_fn = lib.fn(f"{prefix}_residuals", None, [ctypes.c_void_p, _dbl_p])
        self._res = np.zeros(3)  # <P>_residuals writes 3 values (bal/problem.h)
        self._inaccurate_fn = lib.fn(f"{prefix}_inaccurate", ctypes.c_int, [ctypes.c_void_p])
        #: whether an attempt can stop at its acceptable level (else no foreign call)
        self._can_be_inaccurate = bool(info.get("acceptable_stop", True))
        self._layout: Layout | None = None

    def warm_start(self) -> dict[str, np.ndarray]:
        """Copies of the warm start the next solve reads: ``x0``, ``lam_x0``, ``lam_g0``,
        followed by the last solution's ``x``, ``lam_x``, ``lam_g`` — the leading fields of
        the C work struct (``bal/problem.h``, consecutive ``double`` arrays)."""
        nw, ng1 = self.info["nw"], self.info["ng"] + 1
        sizes = {"x0": nw, "lam_x0": nw, "lam_g0": ng1, "x": nw, "lam_x": nw, "lam_g": ng1}
        flat = np.ctypeslib.as_array(ctypes.cast(self.work, _dbl_p),
                                     shape=(sum(sizes.values()),))
        out, k = {}, 0
        for key, n in sizes.items():
            out[key] = flat[k: k + n].copy()
            k += n
        out["lam_g0"], out["lam_g"] = out["lam_g0"][:-1], out["lam_g"][:-1]
        return out

    def inaccurate(self) -> bool:
        """The last solve's ``BAL_OK`` is a stop at the solver's acceptable level
        (``<P>_inaccurate``: the backend's ``optimal_inaccurate``)."""
        return self._can_be_inaccurate and bool(self._inaccurate_fn(self.work))

    def py_status(self, code: int) -> str:
        """The backend's name of this problem's last solve status ``code``
        (:func:`py_status` with :meth:`inaccurate`)."""
        return py_status(code, code == _OK and self.inaccurate())

    def residuals(self) -> tuple[float, float]:
        """Primal violation and dual residual of the last solve."""
        self._res_fn(self.work, _ptr(self._res))
        return float(self._res[0]), float(self._res[1])

    def truncated_feasible(self) -> bool:
        """The last solve's iterate meets every row and bound within
        :data:`~balustrade.backends.solution.FEASIBILITY_TOL` (what
        :func:`balustrade.control.base.feasible_truncation` asks of a truncated solve; the
        C's ``<P>_truncated_feasible`` with the same tolerance, ``<P>_TRUNC_TOL``)."""
        return bool(self.residuals()[0] <= FEASIBILITY_TOL)

    def unpack(self, w: np.ndarray) -> dict[str, np.ndarray]:
        """The user's variables (copies) from the solver's ``x`` (epigraph blocks after; a
        problem in stage order is read through its ``take`` and projected onto the
        layout's bounds, as the backend reports it)."""
        if self._layout is None:
            self._layout = Layout.from_dict(self.info["variables"], self.info["prefix"],
                                            "variable")
        if "take" in self.info:
            w = np.clip(np.asarray(w)[self.info["take"]], self.info["lbx_layout"],
                        self.info["ubx_layout"])
        return {k: np.array(v) for k, v in self._layout.unpack(w[: self._layout.size]).items()}


class _OwnsWork:
    """Frees the C work structure allocated by the library (``self._work``, ``self._free``)
    on :meth:`close` or garbage collection."""

    def _open(self, lib_path: str | Path, manifest: dict | None, kind: str, what: str
              ) -> dict:
        """Load the library (``self._lib``) and return its manifest; a manifest of another
        ``kind`` raises :class:`~balustrade.errors.CodegenError` (``what`` names the
        expected module)."""
        self._lib = _Library(lib_path, manifest)
        m = self._lib.manifest
        if m.get("kind") != kind:
            raise CodegenError(f"{self._lib.path.name}: not an emitted {what} "
                               f"(kind {m.get('kind')!r})")
        return m

    def _allocate(self, prefix: str) -> None:
        """Bind ``<prefix>_free`` and ``<prefix>_reset`` of a control step and allocate its
        work structure (``<prefix>_alloc``; a failure raises
        :class:`~balustrade.errors.CodegenError`)."""
        vp = ctypes.c_void_p
        self._free = self._lib.fn(f"{prefix}_free", None, [vp])
        self._reset = self._lib.fn(f"{prefix}_reset", None, [vp])
        self._work = self._lib.fn(f"{prefix}_alloc", vp, [])()
        if not self._work:
            raise CodegenError(f"{prefix}_alloc failed (no CasADi memory left)")

    def _step_buffers(self) -> None:
        """The step's input/output buffers and its argument tuple
        ``(x, u_p, u, h, &status, work)`` (``self.nx``, ``self.nu`` set)."""
        self._x, self._u_p = np.zeros(self.nx), np.zeros(self.nu)
        self._u, self._h = np.zeros(self.nu), np.zeros(1)
        self._status = ctypes.c_int(0)
        self._args = (_ptr(self._x), _ptr(self._u_p), _ptr(self._u), _ptr(self._h),
                      ctypes.byref(self._status), self._work)

    def close(self) -> None:
        if getattr(self, "_work", None):
            self._free(self._work)
            self._work = None

    def __del__(self) -> None:  # pragma: no cover - interpreter shutdown order
        try:
            self.close()
        except Exception:
            pass


class CProblem(_OwnsWork):
    """An emitted problem (:func:`~balustrade.codegen.emit.emit_problem`, or the problem
    ``problem`` of a module of :func:`~balustrade.codegen.emit.emit_problems`):
    ``solve(params)`` returns ``(status, value, primal dict, w)`` from the C solver,
    warm-started from the previous converged solution unless ``warm=False``."""

    def __init__(self, lib_path: str | Path, manifest: dict | None = None,
                 problem: str | None = None):
        self._lib = _Library(lib_path, manifest)
        m = self._lib.manifest
        kind = m.get("kind")
        if kind not in ("problem", "problems"):
            raise CodegenError(f"{self._lib.path.name}: not an emitted problem "
                               f"(kind {kind!r})")
        key = problem if problem is not None else "problem"
        if key not in m["problems"]:
            raise CodegenError(f"{self._lib.path.name}: no emitted problem {key!r} (have "
                               f"{sorted(m['problems'])}; pass problem=...)")
        self.info = m["problems"][key]
        P = self.info["prefix"]
        self._alloc = self._lib.fn(f"{P}_alloc", ctypes.c_void_p, [])
        self._free = self._lib.fn(f"{P}_free", None, [ctypes.c_void_p])
        self._solve = self._lib.fn(f"{P}_solve", ctypes.c_int, [ctypes.c_void_p, _dbl_p])
        self._cold = self._lib.fn(f"{P}_cold_start", None, [ctypes.c_void_p])
        self._warm = self._lib.fn(f"{P}_warm_start", None, [ctypes.c_void_p])
        self._work = self._alloc()
        if not self._work:
            raise CodegenError(f"{P}_alloc failed (no CasADi memory left)")
        self.view = _CProblemView(self._lib, P, self.info, self._work)
        self._params: Layout | None = None  # the manifest's parameter layout, on first pack
        self._p = np.zeros(max(self.info["np"], 1))
        self._p_ptr = _ptr(self._p)

    def pack(self, params: dict[str, object]) -> np.ndarray:
        """Stack ``params`` in declaration order (declared values fill the missing ones),
        checked as :meth:`balustrade.dsl.OCP.pack_parameters` does: unknown or missing
        names raise :class:`~balustrade.errors.BalustradeError`, a wrong shape
        :class:`~balustrade.errors.ShapeError`, NaN or inf
        :class:`~balustrade.errors.NonFiniteError` — before C is called."""
        if not isinstance(params, dict):
            raise BalustradeError(f"{self.info['prefix']}: parameters must be a dict name -> "
                                  f"value, got {type(params).__name__}")
        if self._params is None:
            self._params = Layout.from_dict(self.info["parameters"], self.info["prefix"],
                                            "parameter")
        return self._params.pack(params)

    def solve(self, params: dict[str, object], warm: bool = True
              ) -> tuple[str, float, dict[str, np.ndarray], np.ndarray]:
        """Solve with named parameters (checked by :meth:`pack` before C runs)."""
        return self.solve_packed(self.pack(params), warm)

    def solve_packed(self, p: np.ndarray, warm: bool = True
                     ) -> tuple[str, float, dict[str, np.ndarray], np.ndarray]:
        """Solve with the stacked parameter vector ``p`` (``np`` values, only its size is
        checked here: a NaN or inf entry reaches the C, which refuses it with
        ``BAL_BAD_INPUT``, status ``"bad_input"``, value NaN)."""
        p = np.asarray(p, dtype=float).reshape(-1)
        if p.size != self.info["np"]:
            raise ShapeError(f"{self.info['prefix']}: stacked parameters",
                             (self.info["np"],), p.shape)
        self._p[: self.info["np"]] = p
        if not warm:
            self._cold(self._work)
        code = self._solve(self._work, self._p_ptr)
        if code in _SOLVED or (code == _TRUNCATED and self.view.truncated_feasible()):
            self._warm(self._work)  # a feasible truncated iterate is continued (real time)
        w = self.view.x.copy()
        value = float(self.view.value_fn(self._work)) if code != _BAD_INPUT else float("nan")
        name = INACCURATE if code == _OK and self.view.inaccurate() else \
            _STATUS.get(code, str(code))
        return name, value, self.view.unpack(w), w

class CPCBFSafetyFilter(_OwnsWork):
    """The emitted PCBF step (2.24)+(2.23) as a closed-loop controller: the same
    ``step(x, u_p) -> (u, StepInfo)`` and ``reset()`` as
    :class:`~balustrade.control.pcbf.PCBFSafetyFilter`, the same fallbacks (computed in C),
    one foreign call per step."""

    def __init__(self, lib_path: str | Path, manifest: dict | None = None,
                 keep_solutions: bool = False):
        m = self._open(lib_path, manifest, "pcbf", "PCBF filter")
        Q = m["name"]
        self.nx, self.nu, self.N = m["nx"], m["nu"], m["N"]
        self.keep_solutions = keep_solutions
        vp = ctypes.c_void_p
        self._step = self._lib.fn(f"{Q}_step", ctypes.c_int,
                                  [_dbl_p, _dbl_p, _dbl_p, _dbl_p,
                                   ctypes.POINTER(ctypes.c_int), vp])
        self._status_fn = self._lib.fn(f"{Q}_solve_status", ctypes.c_int, [vp, ctypes.c_int])
        self._h_upper = self._lib.fn(f"{Q}_h_upper", ctypes.c_double, [vp])
        self._replaced = self._lib.fn(f"{Q}_proposal_replaced", ctypes.c_int, [vp])
        self._allocate(Q)
        slack_ptr = self._lib.fn(f"{Q}_slack_problem", vp, [vp])(self._work)
        filt_ptr = self._lib.fn(f"{Q}_filter_problem", vp, [vp])(self._work)
        self.slack = _CProblemView(self._lib, f"{Q}_slack", m["problems"]["slack"], slack_ptr)
        self.filter = _CProblemView(self._lib, f"{Q}_filter", m["problems"]["filter"],
                                    filt_ptr)
        self._step_buffers()
        # the per-step calls of step(), prebuilt: unchecked handles, converted arguments
        wk = ctypes.c_void_p(self._work)
        self._hot_step = (self._lib.raw(f"{Q}_step", ctypes.c_int), (*self._args[:5], wk))
        status = self._lib.raw(f"{Q}_solve_status", ctypes.c_int)
        self._hot_slack = (status, (wk, ctypes.c_int(0)))
        self._hot_filter = (status, (wk, ctypes.c_int(1)))
        self._hot_replaced = (self._lib.raw(f"{Q}_proposal_replaced", ctypes.c_int), (wk,))
        # the shifted-plan certificate (balustrade.control.shifted), when it was emitted
        self.shifted_certificate = bool(m.get("shifted_certificate", False))
        self._hot_certified = ((self._lib.raw(f"{Q}_shift_certified", ctypes.c_int), (wk,))
                               if self.shifted_certificate else None)
        self._h_solver = self._lib.fn(f"{Q}_h_solver", ctypes.c_double, [vp]) \
            if self.shifted_certificate else None
        # certificate first: (2.24) skipped when the shifted plan certifies h_PB = 0 (on by
        # default in emit_pcbf, which always records it; a manifest without the key comes
        # from a library emitted before the option, whose C cannot skip (2.24))
        self.certificate_first = bool(m.get("certificate_first", False))
        self._hot_first = ((self._lib.raw(f"{Q}_cert_first", ctypes.c_int), (wk,))
                           if self.certificate_first else None)

    def reset(self) -> None:
        """Forget the warm starts (primal and dual, kept in the C work struct across steps)
        and the plan: a new closed loop."""
        self._reset(self._work)

    _BAD = S.code_of(S.PCBF, "bad_input")
    _PCBF_OK = S.code_of(S.PCBF, "ok")

    def step_raw(self, x: np.ndarray, u_p: np.ndarray) -> tuple[np.ndarray, float, int]:
        """One C step without building a StepInfo: ``(u, h_PB, status code)``; the
        returned ``u`` is a view of the output buffer (copy it to keep it)."""
        self._x[:] = x
        self._u_p[:] = u_p
        fn, args = self._hot_step
        code = fn(*args)
        return self._u, float(self._h[0]), code

    def step(self, x: np.ndarray, u_p: np.ndarray) -> tuple[np.ndarray, StepInfo]:
        """One C step, reported as :class:`~balustrade.control.pcbf.PCBFSafetyFilter`
        reports it (status, fallback, ``values["h_PB"]``/``["h_PB_upper"]``,
        ``uncertified``; see :func:`_pcbf_info`; a step on the shifted-plan certificate
        also ``values["shifted_certificate"] = 1`` and ``["h_PB_solver"]``). Wrong shapes raise
        :class:`~balustrade.errors.ShapeError`; a NaN or inf ``x`` is refused by the C
        (``BAL_PCBF_BAD_INPUT``: the proposal, non-finite entries as 0, clipped to ``U``;
        ``"non_finite_state"``); NaN or inf entries of ``u_p`` are read as 0 and the
        step runs as usual (``"non_finite_proposal[_<status>]"``)."""
        finite_u_p = _load(self._u_p, u_p, "CPCBFSafetyFilter.step: u_p", proposal=True)
        _load(self._x, x, "CPCBFSafetyFilter.step: x")
        fn, args = self._hot_step
        start = time.perf_counter()
        code = fn(*args)
        elapsed = time.perf_counter() - start
        fn, args = self._hot_slack
        s_code = fn(*args)
        fn, args = self._hot_filter
        f_code = fn(*args)
        first = fired = 0
        if self._hot_first is not None:
            fn, args = self._hot_first
            first = fn(*args)
        if self._hot_certified is not None and not first:
            fn, args = self._hot_certified
            fired = fn(*args)
        # a BAL_OK that stopped at the solver's acceptable level (optimal_inaccurate)
        f_inacc = f_code == _OK and self.filter.inaccurate()
        s_inacc = s_code == _OK and not first and not fired and self.slack.inaccurate()
        if first:  # (2.24) skipped: "certified", as PCBFSafetyFilter._certified_step
            info = _certified_info(code, f_code, float(self._h[0]),
                                   f_code == _TRUNCATED and self.filter.truncated_feasible(),
                                   f_inacc)
        elif fired:  # the shifted plan was the (2.24) point: an optimal one, as in Python
            info = _pcbf_info(code, _OK, f_code, float(self._h[0]), float("nan"), False,
                              f_code == _TRUNCATED and self.filter.truncated_feasible(),
                              False, f_inacc)
            info.values.update(shifted_certificate=1.0,
                               h_PB_solver=float(self._h_solver(self._work)))
        elif code == self._PCBF_OK and s_code == _OK and f_code == _OK and not s_inacc \
                and not f_inacc:  # _pcbf_info's "ok"
            info = StepInfo(values={"h_PB": float(self._h[0])})
        else:
            # the bound of a merely feasible (2.24) is only read when there is one
            h_upper = float(self._h_upper(self._work)) if s_code in (_FEASIBLE, _TRUNCATED) \
                else float("nan")
            info = _pcbf_info(code, s_code, f_code, float(self._h[0]), h_upper,
                              s_code == _TRUNCATED and self.slack.truncated_feasible(),
                              f_code == _TRUNCATED and self.filter.truncated_feasible(),
                              s_inacc, f_inacc)
        info.solve_time = elapsed
        if code != self._BAD and not finite_u_p:
            fn, args = self._hot_replaced
            replaced = fn(*args)
            if replaced:
                note_proposal(info, replaced)
        if self.keep_solutions:
            info.solutions = {"slack": self.slack.unpack(self.slack.x.copy()),
                              "filter": self.filter.unpack(self.filter.x.copy())}
        return self._u.copy(), info


def _certified_info(code: int, f_code: int, h: float, f_trunc_ok: bool,
                    f_inaccurate: bool = False) -> StepInfo:
    """The :class:`StepInfo` of a step whose (2.24) was skipped on the shifted-plan
    certificate (``certificate_first``), as
    :meth:`~balustrade.control.pcbf.PCBFSafetyFilter._certified_step` records it:
    ``"certified"`` (``"certified_filter_<f>"`` when (2.23) did not end optimal),
    ``values["h_PB"]`` and ``["certificate_first"] = 1``, never a solver status for (2.24)."""
    known = _PCBF_CODES.get(code)
    info = StepInfo(fallback=known.fallback if known is not None else "unknown",
                    values={"h_PB": h, "certificate_first": 1.0})
    f = py_status(f_code, f_inaccurate)
    info.status = "certified" if f == "optimal" else f"certified_filter_{f}"
    if (f_code in _SOLVED or f_trunc_ok) and f != "optimal":
        info.uncertified["filter"] = f
    return info


def _pcbf_info(code: int, s_code: int, f_code: int, h: float, h_upper: float,
               s_trunc_ok: bool = False, f_trunc_ok: bool = False,
               s_inaccurate: bool = False, f_inaccurate: bool = False) -> StepInfo:
    """The :class:`StepInfo` :class:`~balustrade.control.pcbf.PCBFSafetyFilter` records for
    the same decisions, from the C step's code and its two solve statuses: ``status``
    (``"ok"``, ``"slack_<s>"``, ``"slack_<s>_filter_<f>"``, ``"filter_<f>"``, with a
    converged C solve named ``optimal`` and one stopped by its budget ``truncated``),
    ``fallback``, ``h_PB`` (NaN after a merely feasible (2.24), whose cost is
    ``h_PB_upper``) and ``uncertified``. ``s_trunc_ok``/``f_trunc_ok``: the truncated
    (2.24)/(2.23) stopped at a feasible iterate (used as the Python policy uses it).
    ``s_inaccurate``/``f_inaccurate``: the (2.24)/(2.23) ``BAL_OK`` stopped at the solver's
    acceptable level (``optimal_inaccurate``: used, its ``h_PB`` recorded, never
    certified, as pcbf.py)."""
    known = _PCBF_CODES.get(code)
    info = StepInfo(fallback=known.fallback if known is not None else "unknown")
    s_inaccurate, f_inaccurate = s_inaccurate and s_code == _OK, f_inaccurate and f_code == _OK
    s, f = py_status(s_code, s_inaccurate), py_status(f_code, f_inaccurate)
    if known is None:
        info.status = str(code)
        return info
    if known.name == "bad_input":
        info.status = "non_finite_state"
        return info
    s_usable = s_code == _FEASIBLE or s_trunc_ok  # feasible, not converged
    certified = (s_code == _OK and not s_inaccurate) or (s_usable and np.isfinite(h))
    # a truncated (2.24) never makes the step "ok", even when certified by h_PB >= 0
    plain = certified and s_code != _TRUNCATED
    if s_usable and not certified:
        info.uncertified["slack"] = s
        info.values.update(h_PB=float("nan"), h_PB_upper=h_upper)
    elif certified or s_inaccurate:
        if s_inaccurate:
            info.uncertified["slack"] = s
        info.values["h_PB"] = h
    if known.name in ("shifted_plan", "projected_proposal"):
        info.status = f"slack_{s}"
        return info
    if f_code in _SOLVED or f_trunc_ok:
        if f != "optimal":
            info.uncertified["filter"] = f
        info.status = "ok" if plain and f == "optimal" else f"slack_{s}_filter_{f}"
    else:
        info.status = ("" if plain else f"slack_{s}_") + f"filter_{f}"
    return info


def mirror_c_retries(compiled: object, allow_external: bool | None = None) -> object:
    """A copy of a compiled CasADi problem that retries failed solves exactly as its emitted
    C does: the part of its retry chain that has code generation
    (:func:`~balustrade.backends.emittable.c_retry_chain`, the emitters' rule: retries that
    link a library only when the first attempt links one, unless ``allow_external`` says
    otherwise — pass the value the problem was emitted with, e.g. ``full_chain`` of
    :func:`~balustrade.codegen.emit_robust`), so Python and the deployed C can be compared
    step by step. ``compiled`` itself is not changed (it is returned as is when its whole
    chain is emitted)."""
    kept = c_retry_chain(compiled.solver_name, compiled.options, compiled.retries,
                         allow_external)
    return compiled if kept is compiled.retries else compiled.with_retries(kept)


class CApproximatePCBFFilter(_OwnsWork):
    """The emitted Algorithm 7.5 (:func:`~balustrade.codegen.emit.emit_approximate`) as a
    closed-loop controller with the interface and counters of
    :class:`~balustrade.control.approximate.ApproximatePCBFFilter`."""

    _CODES = S.by_code(S.APPROX)
    _BAD = S.code_of(S.APPROX, "bad_input")
    _CERTIFIED = S.code_of(S.APPROX, "certified")
    _FILTER_FEASIBLE = S.code_of(S.APPROX, "filter_feasible")
    _OK = S.code_of(S.APPROX, "ok")

    def __init__(self, lib_path: str | Path, manifest: dict | None = None):
        m = self._open(lib_path, manifest, "approximate", "Algorithm 7.5 filter")
        A, vp = m["name"], ctypes.c_void_p
        self.nx, self.nu = m["nx"], m["nu"]
        self._step = self._lib.fn(f"{A}_step", ctypes.c_int,
                                  [_dbl_p, _dbl_p, _dbl_p, _dbl_p,
                                   ctypes.POINTER(ctypes.c_int), vp])
        self._dh = self._lib.fn(f"{A}_dh", ctypes.c_double, [vp])
        self._counter = self._lib.fn(f"{A}_counter", ctypes.c_long, [vp, ctypes.c_int])
        self._set_certify = self._lib.fn(f"{A}_set_certify", None, [vp, ctypes.c_int])
        self._replaced = self._lib.fn(f"{A}_proposal_replaced", ctypes.c_int, [vp])
        # a (7.5) whose solver can stop at its acceptable level: its BAL_OK is
        # named optimal_inaccurate, as ApproximatePCBFFilter records it
        self._filter_inaccurate = self._lib.fn(f"{A}_inaccurate", ctypes.c_int, [vp]) \
            if m["problems"]["filter"].get("acceptable_stop", True) else None
        self._allocate(A)
        self._step_buffers()

    @property
    def certify(self) -> bool:
        return bool(self._lib.manifest["certify"])

    def set_certify(self, certify: bool) -> None:
        self._set_certify(self._work, int(bool(certify)))
        self._lib.manifest["certify"] = bool(certify)

    def reset(self) -> None:
        self._reset(self._work)

    def __getattr__(self, name: str) -> int:
        keys = ("n_steps", "n_certified", "n_solved", "n_fallbacks", "n_proposal_feasible")
        if name in keys and "_work" in self.__dict__:
            return int(self._counter(self._work, keys.index(name)))
        raise AttributeError(name)

    def step(self, x: np.ndarray, u_p: np.ndarray) -> tuple[np.ndarray, StepInfo]:
        """One C step, reported as the Python controller reports it. Wrong shapes raise
        ShapeError; a NaN or inf ``x``: status ``"non_finite_state"``, the proposal
        (non-finite entries as 0) clipped to ``U``; NaN or inf entries of ``u_p`` are read
        as 0 and the step runs as usual (``"non_finite_proposal[_<status>]"``); a (7.5)
        solve that is only feasible: ``"filter_feasible"``, flagged in ``uncertified``; one
        that stopped at its solver's acceptable level: ``"filter_optimal_inaccurate"``,
        flagged."""
        _load(self._u_p, u_p, "CApproximatePCBFFilter.step: u_p", proposal=True)
        _load(self._x, x, "CApproximatePCBFFilter.step: x")
        start = time.perf_counter()
        code = self._step(*self._args)
        known = self._CODES.get(code)
        info = StepInfo(solve_time=time.perf_counter() - start,
                        fallback=known.fallback if known is not None else "unknown")
        info.status = known.name if known is not None else str(code)
        if code == self._BAD:
            info.status = "non_finite_state"
            return self._u.copy(), info
        info.values["certified"] = 1.0 if code == self._CERTIFIED else 0.0
        if code != self._CERTIFIED:
            info.values.update(h_hat=float(self._h[0]), dh=float(self._dh(self._work)))
        if code == self._FILTER_FEASIBLE:
            info.uncertified["filter"] = "feasible"
        elif code == self._OK and self._filter_inaccurate is not None and \
                self._filter_inaccurate(self._work):
            # approximate.py: note_solve(info, "filter", "optimal_inaccurate") -> flagged
            info.status, info.uncertified["filter"] = f"filter_{INACCURATE}", INACCURATE
        note_proposal(info, int(self._replaced(self._work)))
        return self._u.copy(), info
