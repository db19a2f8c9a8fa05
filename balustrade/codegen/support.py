"""Which CasADi solvers and functions can be emitted as C, checked before generating.

Facts (CasADi 3.8, checked by generating and compiling each plugin on a small NLP):

============================  =========================================================
solver                         generated C
============================  =========================================================
``sqpmethod`` + ``qrqp``       self-contained: needs only ``libm`` (what balustrade builds)
``sqpmethod`` + ``osqp``       calls OSQP: needs ``<osqp/osqp.h>`` and ``libosqp``
``sqpmethod`` + ``daqp``       calls DAQP: needs ``<daqp/api.h>`` and ``libdaqp``
``sqpmethod`` + ``highs``      calls HiGHS: needs ``<interfaces/highs_c_api.h>``, ``libhighs``
``sqpmethod`` + ``hpipm``      calls HPIPM: needs ``libhpipm`` and ``libblasfeo``
``fatrop``                     calls FATROP: needs ``libfatrop`` and ``libblasfeo``
``ipopt``                      refused: the C only wraps IPOPT's C interface (``libipopt``,
                               MUMPS, dynamic memory) — nothing embeddable is generated
``sqpmethod`` + ``qpoases``    refused: the generated file contains ``#error Code
                               generation not supported for QpoasesInterface``
``feasiblesqpmethod``          refused: its generated C does not compile (CasADi 3.8)
others                         refused (no code generation in CasADi)
============================  =========================================================

A function graph that calls a Python ``casadi.Callback`` is refused too: CasADi only warns
("cannot be code generated") and writes C that does not compile.
"""

from __future__ import annotations

import casadi as ca

from balustrade.errors import CodegenError

#: (nlpsol plugin, qpsol plugin or None) -> libraries the generated C must be linked with
#: (empty: self-contained, needs only libm).
SUPPORTED: dict[tuple[str, str | None], tuple[str, ...]] = {
    ("sqpmethod", "qrqp"): (),
    ("sqpmethod", "osqp"): ("osqp",),
    ("sqpmethod", "daqp"): ("daqp",),
    ("sqpmethod", "highs"): ("highs",),
    ("sqpmethod", "hpipm"): ("hpipm", "blasfeo"),
    ("fatrop", None): ("fatrop", "blasfeo"),
}

#: plugins known to have no usable code generation, with the reason shown to the user.
REFUSED: dict[str, str] = {
    "ipopt": "CasADi only emits a wrapper around IPOPT's C interface (libipopt with MUMPS "
             "and dynamic memory), not a self-contained solver",
    "qpoases": "CasADi's qpOASES interface has no code generation (the generated file "
               "contains '#error Code generation not supported')",
    "feasiblesqpmethod": "the C that CasADi 3.8 generates for it does not compile",
    "blocksqp": "CasADi has no code generation for blockSQP",
    "scpgen": "CasADi has no code generation for scpgen",
    "bonmin": "CasADi has no code generation for Bonmin",
}

#: what to use instead, appended to every refusal.
ADVICE = ("compile the problem with solver='sqpmethod' (qpsol 'qrqp', the default in "
          "balustrade.backends), which generates self-contained C needing only libm")

_SQP_DEFAULT_QPSOL = "qpoases"  # CasADi's default qpsol for sqpmethod


def solver_libraries(plugin: str, options: dict | None = None, what: str = "problem",
                     allow_external: bool = False) -> tuple[str, ...]:
    """Check that the nlpsol ``plugin`` (with its ``qpsol`` option) generates C and return
    the libraries that C needs (empty for self-contained).

    Raises :class:`~balustrade.errors.CodegenError` naming ``what`` for plugins without code
    generation, and for ones that need an external library unless ``allow_external``.
    """
    options = options or {}
    qpsol = options.get("qpsol", _SQP_DEFAULT_QPSOL) if plugin == "sqpmethod" else None
    if plugin in REFUSED:
        raise CodegenError(f"{what}: solver {plugin!r} cannot be emitted as C: "
                           f"{REFUSED[plugin]}; {ADVICE}")
    if qpsol in REFUSED:
        raise CodegenError(f"{what}: sqpmethod with qpsol {qpsol!r} cannot be emitted as C: "
                           f"{REFUSED[qpsol]}; {ADVICE}")
    key = (plugin, qpsol)
    if key not in SUPPORTED:
        name = plugin if qpsol is None else f"{plugin} with qpsol {qpsol!r}"
        raise CodegenError(f"{what}: solver {name} has no known C code generation; {ADVICE}")
    libs = SUPPORTED[key]
    if libs and not allow_external:
        name = plugin if qpsol is None else f"{plugin}+{qpsol}"
        raise CodegenError(f"{what}: the C generated for {name} must be linked with "
                           f"{', '.join('lib' + lib for lib in libs)} (not self-contained); "
                           f"pass allow_external=True and give build() the include and "
                           f"library flags, or {ADVICE}")
    return libs


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
