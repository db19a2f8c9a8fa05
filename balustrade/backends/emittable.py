"""Which CasADi solvers generate C, what that C links with, and which retries it runs.

These are facts about solvers, so they live in ``backends/`` (issue #13, §1): the code
generator (:mod:`balustrade.codegen`) asks a target (:meth:`Target.emit_reason
<balustrade.backends.targets.Target.emit_reason>`, :meth:`Target.c_libraries
<balustrade.backends.targets.Target.c_libraries>`) or the functions below instead of
checking solver names itself.

Facts (CasADi 3.8, checked by generating and compiling each plugin on a small NLP):

============================  =========================================================
solver                         generated C
============================  =========================================================
``sqpmethod`` + ``qrqp``       self-contained: needs only ``libm`` (the ``fast-sqp`` target)
``sqpmethod`` + ``osqp``       calls OSQP: needs ``<osqp/osqp.h>`` and ``libosqp``
``sqpmethod`` + ``daqp``       calls DAQP: needs ``<daqp/api.h>`` and ``libdaqp``
``sqpmethod`` + ``highs``      calls HiGHS: needs ``<interfaces/highs_c_api.h>``, ``libhighs``
``sqpmethod`` + ``hpipm``      calls HPIPM: needs ``libhpipm`` and ``libblasfeo``
``fatrop``                     calls FATROP: needs ``libfatrop`` and ``libblasfeo``
``ipopt``                      calls IPOPT's C interface: needs ``<coin-or/IpStdCInterface.h>``
                               and ``libipopt`` (with MUMPS; allocates memory, not for
                               embedded targets). Used as the last retry of the sqpmethod
                               chain, so the C runs the chain Python runs (issue #16)
``sqpmethod`` + ``qpoases``    refused: the generated file contains ``#error Code
                               generation not supported for QpoasesInterface``
``feasiblesqpmethod``          refused: its generated C does not compile (CasADi 3.8)
others                         refused (no code generation in CasADi)
============================  =========================================================
"""

from __future__ import annotations

import re
from collections.abc import Mapping

from balustrade.backends.casadi_backend import EMITTED_STOP_OPTIONS, solver_options

#: (nlpsol plugin, qpsol plugin or None) -> libraries the generated C must be linked with
#: (empty: self-contained, needs only libm).
SUPPORTED: dict[tuple[str, str | None], tuple[str, ...]] = {
    ("sqpmethod", "qrqp"): (),
    ("sqpmethod", "osqp"): ("osqp",),
    ("sqpmethod", "daqp"): ("daqp",),
    ("sqpmethod", "highs"): ("highs",),
    ("sqpmethod", "hpipm"): ("hpipm", "blasfeo"),
    ("fatrop", None): ("fatrop", "blasfeo"),
    ("ipopt", None): ("ipopt",),
}

#: options that make a plugin's generated C return the solver's own convergence verdict (0:
#: converged, nonzero: not), for plugins whose C cannot be judged by the KKT residuals the
#: emitted step computes: IPOPT converges on its internally scaled problem (dual
#: infeasibility relative to the multipliers' size), so its unscaled dual residual can
#: exceed sqpmethod's ``tol_du`` at a point IPOPT (and the backend) calls optimal.
#: ``error_on_fail`` counts IPOPT's "solved to acceptable level" as converged, which the
#: backend reports ``optimal_inaccurate`` (never used as optimal). The emitted IPOPT (and
#: the IPOPT retry of an as-emitted target in Python, :data:`~balustrade.backends.
#: casadi_backend.EMITTED_STOP_OPTIONS`) has ``acceptable_iter`` 0, which switches off the
#: acceptable stop after a run of acceptable iterates — it does not stop IPOPT from ending
#: at the acceptable level otherwise: measured on the lane change (seed 8, the (5.16)
#: retry) IPOPT returned ``Solved_To_Acceptable_Level`` after 82 iterations with it (IPOPT
#: stops there when its line search would call the restoration phase at an acceptable
#: point). The C tells that stop from success by IPOPT's own return status
#: (:data:`ACCEPTABLE_STOP`, :func:`status_accessors`): ``BAL_OK`` with ``<P>_inaccurate``,
#: named ``optimal_inaccurate`` as by the backend (session 13; tests/test_ipopt_status.py).
STATUS_OPTIONS: dict[str, dict] = {"ipopt": {"error_on_fail": True,
                                             **EMITTED_STOP_OPTIONS["ipopt"]},
                                    # fatrop: its generated C returns nonzero unless fatrop
                                    # itself ended with Success (an acceptable stop
                                    # included: the C then retries it, never uses it)
                                    "fatrop": {"error_on_fail": True}}

#: plugins whose generated C keeps the solver's own return status in its memory struct
#: (CasADi 3.8.2: ``struct casadi_ipopt_data`` has ``enum ApplicationReturnStatus status``,
#: set by ``casadi_ipopt_solve``, in the file-static array ``casadi_f<N>_mem``), with the
#: value of that status that means "stopped at the acceptable level": IPOPT's
#: ``Solved_To_Acceptable_Level`` = 1 (``IpReturnCodes_inc.h``). The generated solver returns
#: 0 (converged) for it as for ``Solve_Succeeded`` (``error_on_fail`` counts it converged),
#: so the emitters add an accessor (:func:`status_accessors`) and ``bal/problem.c`` reports
#: that stop as the backend does: ``optimal_inaccurate`` (``Status.OPTIMAL_INACCURATE``),
#: never as optimal (session 13).
ACCEPTABLE_STOP: dict[str, int] = {"ipopt": 1}

#: CasADi's class name of an nlpsol plugin -> the plugin (for the plugins of
#: :data:`ACCEPTABLE_STOP`)
_PLUGIN_CLASS: dict[str, str] = {"IpoptInterface": "ipopt"}

#: suffix of the accessor of a solver's own return status (``<symbol>_return_status(mem)``)
RETURN_STATUS_SUFFIX = "_return_status"


def status_accessors(c_text: str, h_text: str, classes: Mapping[str, str]) -> tuple[str, str]:
    """The generated C (``c_text``) and header (``h_text``) with, for every solver symbol of
    ``classes`` (C symbol -> CasADi class name) whose plugin is in :data:`ACCEPTABLE_STOP`,
    an exported ``int <symbol>_return_status(int mem)``: the solver's own return status of
    its last run on memory ``mem``. The memory array is found through the symbol's exported
    wrapper (``return casadi_f<N>(arg, res, iw, w, mem);``); a symbol whose wrapper is not
    found raises ValueError (a CasADi whose generated C has another shape)."""
    defs, decls = [], []
    for sym, cls in classes.items():
        if _PLUGIN_CLASS.get(cls) not in ACCEPTABLE_STOP:
            continue
        m = re.search(r"int " + re.escape(sym) + r"\(const casadi_real\*\* arg[^)]*\)\s*\{"
                      r"\s*return (casadi_f\d+)\(arg, res, iw, w, mem\);", c_text)
        if m is None or f"static struct casadi_ipopt_data {m.group(1)}_mem[" not in c_text:
            raise ValueError(f"{sym}: the generated C has no IPOPT memory to read its return "
                             f"status from (CasADi's code generation changed?)")
        fn = f"{sym}{RETURN_STATUS_SUFFIX}"
        defs.append(f"/* balustrade: {sym}'s own return status (IPOPT's "
                    f"ApplicationReturnStatus) of its last run on memory mem */\n"
                    f"CASADI_SYMBOL_EXPORT int {fn}(int mem) {{\n"
                    f"  return (int) {m.group(1)}_mem[mem].status;\n}}\n")
        decls.append(f"int {fn}(int mem);\n")
    if not defs:
        return c_text, h_text
    tail = '#ifdef __cplusplus\n} /* extern "C" */\n#endif'
    cut = h_text.rfind(tail)
    h_text = h_text[:cut] + "".join(decls) + h_text[cut:] if cut >= 0 else \
        h_text + "".join(decls)
    return c_text + "\n" + "\n".join(defs), h_text


#: blocks of C that CasADi 3.8 writes with *every* solver of a plugin it generates (fatrop's
#: print callbacks): with two such solvers in one file (a PCBF pair) the C redefines them and
#: does not compile, so the emitters keep the first copy (:func:`once_per_file`)
ONCE_PER_FILE: tuple[str, ...] = (
    "void casadi_fatrop_cb_write(const char* msg, int num) {\n"
    "  CASADI_PRINTF(\"%.*s\", num, msg);\n}\n"
    "void casadi_fatrop_cb_flush(void) {\n}\n",)

#: include folders (under the casadi wheel's ``include/``) that a library's generated C needs
#: besides ``include/`` itself: fatrop's headers include each other relative to their folder
INCLUDE_SUBDIRS: dict[str, tuple[str, ...]] = {"fatrop": ("fatrop",)}


def once_per_file(text: str) -> str:
    """Generated C ``text`` with every block of :data:`ONCE_PER_FILE` kept once (its first
    occurrence)."""
    for block in ONCE_PER_FILE:
        first = text.find(block)
        if first >= 0:
            cut = first + len(block)
            text = text[:cut] + text[cut:].replace(block, "")
    return text


def include_subdirs(libraries: tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """The extra include folders (:data:`INCLUDE_SUBDIRS`) of ``libraries``."""
    return tuple(d for lib in libraries for d in INCLUDE_SUBDIRS.get(lib, ()))


#: plugins known to have no usable code generation, with the reason shown to the user.
REFUSED: dict[str, str] = {
    "qpoases": "CasADi's qpOASES interface has no code generation (the generated file "
               "contains '#error Code generation not supported')",
    "feasiblesqpmethod": "the C that CasADi 3.8 generates for it does not compile",
    "blocksqp": "CasADi has no code generation for blockSQP",
    "scpgen": "CasADi has no code generation for scpgen",
    "bonmin": "CasADi has no code generation for Bonmin",
}

#: what to use instead, appended to every refusal.
ADVICE = ("compile the problem for the 'fast-sqp' target (sqpmethod with qpsol 'qrqp', the "
          "default in balustrade.backends), which generates self-contained C needing only libm")

_SQP = "sqpmethod"
_SQP_DEFAULT_QPSOL = "qpoases"  # CasADi's own default qpsol for sqpmethod


def _qpsol(solver: str, options: Mapping) -> str | None:
    return options.get("qpsol", _SQP_DEFAULT_QPSOL) if solver == _SQP else None


def codegen_reason(solver: str, options: Mapping | None = None,
                   allow_external: bool = False) -> str | None:
    """Why the CasADi ``solver`` with ``options`` (as passed to ``nlpsol``) cannot be emitted
    as C, or ``None`` if it can; with ``allow_external=False`` a solver whose C must be
    linked with an external library is refused too."""
    options = options or {}
    qpsol = _qpsol(solver, options)
    if solver in REFUSED:
        return f"solver {solver!r} cannot be emitted as C: {REFUSED[solver]}; {ADVICE}"
    if qpsol in REFUSED:
        return (f"{solver} with qpsol {qpsol!r} cannot be emitted as C: {REFUSED[qpsol]}; "
                f"{ADVICE}")
    if (solver, qpsol) not in SUPPORTED:
        name = solver if qpsol is None else f"{solver} with qpsol {qpsol!r}"
        return f"solver {name} has no known C code generation; {ADVICE}"
    libs = SUPPORTED[solver, qpsol]
    if libs and not allow_external:
        name = solver if qpsol is None else f"{solver}+{qpsol}"
        return (f"the C generated for {name} must be linked with "
                f"{', '.join('lib' + lib for lib in libs)} (not self-contained); "
                f"pass allow_external=True and give build() the include and "
                f"library flags, or {ADVICE}")
    return None


def c_libraries(solver: str, options: Mapping | None = None) -> tuple[str, ...]:
    """The libraries the C generated for ``solver`` must be linked with (empty:
    self-contained); ``()`` also for solvers without code generation (ask
    :func:`codegen_reason` first)."""
    return SUPPORTED.get((solver, _qpsol(solver, options or {})), ())


def full_options(solver: str, options: Mapping | None = None) -> dict:
    """The options ``nlpsol`` receives for ``solver``: the backend's defaults updated by
    ``options`` (:func:`~balustrade.backends.casadi_backend.solver_options`)."""
    return solver_options(solver, dict(options or {}))


def c_retries(solver: str, options: Mapping, retries: list[tuple[str, Mapping]],
              allow_external: bool = False) -> list[tuple[str, dict, dict, str]]:
    """The cold-start retries the C emitted for a compiled problem runs: the entries of its
    retry chain ``retries`` (``(solver, option overrides)``, as the backend runs them after
    a failed first attempt of ``solver`` with the full ``options``) whose C can be generated
    (:func:`codegen_reason`; one that links an external library only with
    ``allow_external``), in order, as ``(plugin, overrides, full nlpsol options, label)``.
    The options are those the backend builds the retry with: ``options`` updated by the
    overrides for the same plugin, the plugin's defaults updated by them for another
    (:func:`~balustrade.backends.casadi_backend.solver_options`). With the whole chain
    emittable, Python and its C run the same chain (no mirror needed)."""
    out = []
    for name, over in retries:
        over = dict(over)
        opts = {**options, **over} if name == solver else full_options(name, over)
        if codegen_reason(name, opts, allow_external) is None:
            label = str(over.get("convexify_strategy", name)) if name == _SQP else name
            out.append((name, over, opts, label))
    return out


def retries_link_libraries(solver: str, options: Mapping) -> bool:
    """The default rule for which retries emitted C runs: retries that link an external
    library are emitted when the first attempt links one (the user already links
    libraries for this problem), else only self-contained ones."""
    return bool(c_libraries(solver, options))


def c_retry_chain(solver: str, options: Mapping, retries: list[tuple[str, dict]],
                  allow_external: bool | None = None) -> list[tuple[str, dict]]:
    """The part of a compiled problem's retry chain that its emitted C runs too, as
    ``(solver, overrides)``: :func:`c_retries` with ``allow_external`` (default
    :func:`retries_link_libraries`), the rule the emitters use. The same list object when
    the whole chain is emitted."""
    if allow_external is None:
        allow_external = retries_link_libraries(solver, options)
    kept = [(name, over) for name, over, _, _ in c_retries(solver, options, retries,
                                                           allow_external)]
    same = len(kept) == len(retries) and all(
        a == b and dict(x) == dict(y) for (a, x), (b, y) in zip(kept, retries))
    return retries if same else kept


__all__ = ["ACCEPTABLE_STOP", "ADVICE", "INCLUDE_SUBDIRS", "ONCE_PER_FILE", "REFUSED",
           "RETURN_STATUS_SUFFIX", "STATUS_OPTIONS", "SUPPORTED", "c_libraries", "c_retries",
           "c_retry_chain", "codegen_reason", "full_options", "include_subdirs",
           "once_per_file", "retries_link_libraries", "status_accessors"]
