"""Checks before generating C: solvers (asked of :mod:`balustrade.backends`) and callbacks.

Which solvers generate C and which libraries that C needs are facts about solvers, kept in
:mod:`balustrade.backends.emittable` (asked through a compiled problem's target,
:meth:`~balustrade.backends.Target.emit_reason`); :func:`solver_libraries` is the same check
by solver name and options. A function graph that calls a Python ``casadi.Callback`` is
refused too: CasADi only warns ("cannot be code generated") and writes C that does not
compile.
"""

from __future__ import annotations

import casadi as ca

from balustrade.backends.emittable import ADVICE, REFUSED, SUPPORTED, c_libraries, codegen_reason
from balustrade.errors import CodegenError


def solver_libraries(plugin: str, options: dict | None = None, what: str = "problem",
                     allow_external: bool = False) -> tuple[str, ...]:
    """Check that the CasADi solver ``plugin`` (with its options, as given to ``nlpsol``)
    generates C and return the libraries that C needs (empty for self-contained).

    Raises :class:`~balustrade.errors.CodegenError` naming ``what`` for solvers without code
    generation, and for ones that need an external library unless ``allow_external``.
    """
    reason = codegen_reason(plugin, options, allow_external)
    if reason is not None:
        raise CodegenError(f"{what}: {reason}")
    return c_libraries(plugin, options)


def check_no_callbacks(fn: ca.Function, what: str) -> None:
    """Refuse a function whose graph calls a Python ``casadi.Callback`` (or a loaded
    ``casadi.external``), directly or through nested functions and solver oracles."""
    seen: set[int] = set()
    path: list[str] = []

    def visit(f: ca.Function) -> None:
        key = hash((f.name(), f.class_name(), f.n_in(), f.n_out(), f.nnz_in(), f.nnz_out()))
        if key in seen:
            return
        seen.add(key)
        path.append(f.name())
        cls = f.class_name()
        if cls == "CallbackInternal":
            raise CodegenError(f"{what}: {' -> '.join(path)} is a Python casadi.Callback; "
                               "its body is Python and cannot be emitted as C. Write it as a "
                               "CasADi expression (SX/MX) instead")
        if cls in ("External", "GenericExternal"):
            raise CodegenError(f"{what}: {' -> '.join(path)} is a casadi.external loaded "
                               "from a compiled library; emit its source instead")
        if f.is_a("MXFunction"):
            for k in range(f.n_instructions()):
                mx = f.instruction_MX(k)
                if mx.is_call():
                    visit(mx.which_function())
        try:
            names = f.get_function()
        except RuntimeError:  # pragma: no cover - functions without dependencies
            names = []
        for name in names:
            visit(f.get_function(name))
        path.pop()

    visit(fn)


#: ADVICE, REFUSED and SUPPORTED are re-exported from :mod:`balustrade.backends.emittable`
__all__ = ["ADVICE", "REFUSED", "SUPPORTED", "check_no_callbacks", "solver_libraries"]
