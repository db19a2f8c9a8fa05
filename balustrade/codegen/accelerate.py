"""Python closed loops at C speed: :func:`accelerate` turns a controller into its emitted C.

``accelerate(controller)`` emits the controller's step (one C call per control step), builds
it into a shared library, loads it and returns the ctypes controller of
:mod:`~balustrade.codegen.runtime` with the same ``step(x, u_p) -> (u, StepInfo)`` and
``reset()``: a closed loop (:func:`~balustrade.control.simulate`) keeps its Python code and
runs the deployed C. Warm primal–dual starts stay in the C work struct across steps;
``reset()`` clears them.

Which controllers: a registry keyed by controller type (:func:`register`; the most derived
registered class of the controller's MRO wins). Built in:
:class:`~balustrade.control.pcbf.PCBFSafetyFilter` (:func:`~balustrade.codegen.emit.emit_pcbf`),
:class:`~balustrade.control.approximate.ApproximatePCBFFilter` (Algorithm 7.5,
:func:`~balustrade.codegen.emit.emit_approximate`) and
:class:`~balustrade.control.approximate.GridPCBFFilter` (Algorithm 8.7,
:func:`~balustrade.codegen.emit_grid.emit_grid`), the robust filter of Algorithm 5.2
(:func:`~balustrade.codegen.emit_robust.emit_robust`) and Algorithm 6.4
(:func:`~balustrade.codegen.emit_robust.emit_multiobjective`), the last two when built on
an emittable target, Algorithm 6.3 (:class:`~balustrade.control.multiobjective.
MultiobjectiveLyapunovController` built with ``target="convex-qp"``,
:func:`~balustrade.codegen.emit_mo_lyap.emit_mo_lyapunov`) and Algorithm 4.1
(:class:`~balustrade.control.rapsf.RAPSF` on the default target with (4.5) hot-started in
C, or built with ``target="convex-qp"``, :func:`~balustrade.codegen.emit_rapsf.emit_rapsf`;
its C links a QP solver library from the casadi wheel, the flags come from its manifest).
Emitters of further controllers plug in with ``register(cls, emit, load)``.

Cache: the generated sources are hashed (with the compiler flags); the library is built once
per hash into ``build_dir/<name>-<hash>/`` (default: ``$BALUSTRADE_CACHE`` or
``<tmp>/balustrade-<uid>/accelerate``), so a second call with the same controller only
re-emits (CasADi code generation, no compiler) and loads.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from balustrade.codegen.build import BASE_FLAGS, THREAD_FLAGS, _flags, build
from balustrade.codegen.emit import Emitted, emit_approximate, emit_pcbf
from balustrade.codegen.emit_grid import emit_grid
from balustrade.codegen.emit_mo_lyap import emit_mo_lyapunov
from balustrade.codegen.emit_rapsf import emit_rapsf
from balustrade.codegen.emit_robust import emit_multiobjective, emit_robust
from balustrade.codegen.runtime import CApproximatePCBFFilter, CPCBFSafetyFilter
from balustrade.codegen.runtime_grid import CGridPCBFFilter
from balustrade.codegen.runtime_mo_lyap import CMultiobjectiveLyapunovController
from balustrade.codegen.runtime_rapsf import CRAPSF
from balustrade.codegen.runtime_robust import CMultiobjectivePCBFFilter, CRobustPCBFSafetyFilter
from balustrade.control.approximate import ApproximatePCBFFilter, GridPCBFFilter
from balustrade.control.multiobjective import (
    MultiobjectiveLyapunovController,
    MultiobjectivePCBFController,
)
from balustrade.control.pcbf import PCBFSafetyFilter
from balustrade.control.rapsf import RAPSF
from balustrade.control.robust import RobustPCBFSafetyFilter
from balustrade.errors import CodegenError

#: ``emit(controller, name, out_dir) -> Emitted``
EmitFn = Callable[[object, str, Path], Emitted]
#: ``load(lib_path, manifest) -> controller`` with ``step`` and ``reset``
LoadFn = Callable[[Path, dict], object]


@dataclass(frozen=True)
class Accelerator:
    """How one controller type becomes C: its emitter, its loader, the default C name."""

    emit: EmitFn
    load: LoadFn
    name: str


_REGISTRY: dict[type, Accelerator] = {}


def register(controller_type: type, emit: EmitFn, load: LoadFn, name: str) -> None:
    """Make :func:`accelerate` handle ``controller_type`` (and its subclasses without an
    entry of their own): ``emit(controller, name, out_dir)`` writes the C module,
    ``load(lib_path, manifest)`` returns the ctypes controller; ``name`` is the default C
    symbol prefix."""
    if not isinstance(controller_type, type):
        raise CodegenError(f"register: controller_type must be a class, got "
                           f"{type(controller_type).__name__}")
    if not (callable(emit) and callable(load)):
        raise CodegenError("register: emit and load must be callables")
    if not (isinstance(name, str) and name.isidentifier() and name.isascii()):
        raise CodegenError(f"register: name {name!r} must be an ASCII C identifier")
    _REGISTRY[controller_type] = Accelerator(emit, load, name)


def registered() -> tuple[type, ...]:
    """The controller types :func:`accelerate` handles."""
    return tuple(_REGISTRY)


def _accelerator(controller: object) -> Accelerator:
    for cls in type(controller).__mro__:
        if cls in _REGISTRY:
            return _REGISTRY[cls]
    have = ", ".join(sorted(c.__name__ for c in _REGISTRY))
    hint = ""
    if callable(getattr(controller, "deployment_spec", None)):
        hint = (" (its compiled problems can still be emitted one by one: "
                "balustrade.codegen.emit_problems(controller, ...))")
    raise CodegenError(f"accelerate: no C emitter for a {type(controller).__name__}: its "
                       f"closed-loop step has no emitted C{hint}; emitters exist for {have}")


def default_build_dir() -> Path:
    """``$BALUSTRADE_CACHE/accelerate``, else ``<tmp>/balustrade-<uid>/accelerate``."""
    root = os.environ.get("BALUSTRADE_CACHE")
    if root:
        return Path(root) / "accelerate"
    uid = os.getuid() if hasattr(os, "getuid") else "user"
    return Path(tempfile.gettempdir()) / f"balustrade-{uid}" / "accelerate"


def source_hash(src_dir: Path, flags: tuple[str, ...]) -> str:
    """SHA-256 of every generated file of ``src_dir`` (relative path and bytes, sorted; the
    ``bal/`` static C included) and of the compiler flags."""
    h = hashlib.sha256("\0".join(flags).encode())
    for path in sorted(p for p in src_dir.rglob("*") if p.is_file()):
        h.update(str(path.relative_to(src_dir)).encode() + b"\0")
        h.update(path.read_bytes())
        h.update(b"\0")
    return h.hexdigest()


def accelerate(controller: object, build_dir: str | Path | None = None,
               name: str | None = None, werror: bool = False,
               extra_flags: tuple[str, ...] = ()) -> object:
    """The controller's step as emitted C, loaded through ctypes (module docstring).

    Returns the runtime controller (e.g. :class:`~balustrade.codegen.CPCBFSafetyFilter`)
    in its reset state, with ``accelerated``, a dict: ``dir`` (sources and library),
    ``hash``, ``cached`` (the library was already built), ``emit_s``, ``build_s``.
    A controller without a registered emitter, or whose problems cannot be emitted (e.g.
    compiled for cvxpy), raises :class:`~balustrade.errors.CodegenError` saying why. A
    solver chain that needs a library of the casadi wheel (the interior-point last resort,
    the structured targets' solver) is emitted linked to it: the manifest's ``link_flags``
    go into the build (for a PCBF filter this is always allowed; the other emitters follow
    their own rules, e.g. ``emit_robust(full_chain=...)``)."""
    acc = _accelerator(controller)
    name = acc.name if name is None else name
    if build_dir is not None and not isinstance(build_dir, (str, os.PathLike)):
        raise CodegenError(f"accelerate: build_dir must be a path (str or Path), got "
                           f"{type(build_dir).__name__}")
    extra_flags = _flags(extra_flags, "accelerate")
    root = default_build_dir() if build_dir is None else Path(build_dir)
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CodegenError(f"accelerate: cannot create the build folder {str(root)!r}: "
                           f"{exc.strerror or exc}") from exc
    flags = (*BASE_FLAGS, *THREAD_FLAGS, *(["-Werror"] if werror else []), *extra_flags)
    start = time.perf_counter()
    staging = Path(tempfile.mkdtemp(prefix=".staging-", dir=root))
    try:
        emitted = acc.emit(controller, name, staging)
        emit_s = time.perf_counter() - start
        # a solver library the C links (Algorithm 4.1's QP solver): its flags
        extra_flags = (*extra_flags, *emitted.manifest.get("link_flags", ()))
        flags = (*flags, *emitted.manifest.get("link_flags", ()))
        digest = source_hash(staging, flags)
        final = root / f"{name}-{digest[:20]}"
        lib = final / f"lib{name}.so"
        cached = lib.is_file()
        if not cached:
            if final.exists():  # an interrupted earlier build: start over
                shutil.rmtree(final, ignore_errors=True)
            try:
                staging.rename(final)
            except OSError:  # another process got there first
                pass
            tmp = final / f".lib{name}.{os.getpid()}.so"
            build(final, name, werror=werror, extra_flags=extra_flags, out=tmp)
            os.replace(tmp, lib)  # atomic: a concurrent reader sees all or nothing
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    build_s = time.perf_counter() - start - emit_s
    loaded = acc.load(lib, emitted.manifest)
    loaded.reset()
    loaded.accelerated = {"dir": final, "hash": digest, "cached": cached,
                          "emit_s": emit_s, "build_s": build_s}
    return loaded


# (allow_external: a filter whose chain needs a solver library of the casadi wheel — a
# structured target, the interior-point last resort — links it with the manifest's
# link_flags; self-contained targets link nothing)
register(PCBFSafetyFilter, lambda c, n, d: emit_pcbf(c, n, d, allow_external=True),
         CPCBFSafetyFilter, "bal_pcbf")
register(ApproximatePCBFFilter, lambda c, n, d: emit_approximate(c, n, d),
         CApproximatePCBFFilter, "bal_approx")
register(GridPCBFFilter, lambda c, n, d: emit_grid(c, n, d), CGridPCBFFilter, "bal_grid")
register(RobustPCBFSafetyFilter, lambda c, n, d: emit_robust(c, n, d),
         CRobustPCBFSafetyFilter, "bal_robust")
register(MultiobjectivePCBFController, lambda c, n, d: emit_multiobjective(c, n, d),
         CMultiobjectivePCBFFilter, "bal_multiobj")
register(MultiobjectiveLyapunovController, lambda c, n, d: emit_mo_lyapunov(c, n, d),
         CMultiobjectiveLyapunovController, "bal_mo_lyap")


def _emit_rapsf(controller: RAPSF, name: str, out_dir: Path) -> Emitted:
    """:func:`emit_rapsf`, with the controller kept (in memory only) as the manifest's
    ``_host``: :class:`CRAPSF` runs a copy of its estimator for Θ_k."""
    emitted = emit_rapsf(controller, name, out_dir)
    emitted.manifest["_host"] = controller
    return emitted


register(RAPSF, _emit_rapsf, CRAPSF, "bal_rapsf")

__all__ = ["Accelerator", "accelerate", "default_build_dir", "register", "registered",
           "source_hash"]
