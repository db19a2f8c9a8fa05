"""Emit C from compiled CasADi problems and functions; build it; call it from Python.

Deploy path (see ``docs/deploy_c.md``)::

    from balustrade.codegen import emit_pcbf, build, CPCBFSafetyFilter
    emitted = emit_pcbf(controller, "pend", "out/pend", dynamics=system.function)
    lib = build(emitted.out_dir)                 # cc -O3 -fPIC -shared ... -lm
    c_filter = CPCBFSafetyFilter(lib)            # same Controller protocol, C inside
    trace = simulate(system, c_filter, x0, 100, proposal=2.0)

Modules: :mod:`~balustrade.codegen.support` (which solvers generate C, callback check),
:mod:`~balustrade.codegen.emit` (the emitters: plain functions, one problem, the PCBF
pair (2.24)+(2.23), Algorithm 7.5 with (7.5)+(7.6); :mod:`~balustrade.codegen.emit_robust`:
Algorithms 5.2 and 6.4, loaded by :mod:`~balustrade.codegen.runtime_robust`;
reading the controllers' typed deployment specs of :mod:`balustrade.control.deploy`),
:mod:`~balustrade.codegen.cfiles`
(the static C shipped in ``codegen/c/`` and the generated config header that instantiates
it), :mod:`~balustrade.codegen.status` (status codes, defined once),
:mod:`~balustrade.codegen.build` (compiler), :mod:`~balustrade.codegen.runtime` (ctypes).
Algorithm 6.3: :mod:`~balustrade.codegen.emit_mo_lyap` and
:mod:`~balustrade.codegen.runtime_mo_lyap`.
Algorithm 8.7 (grid filter): :mod:`~balustrade.codegen.emit_grid` and
:mod:`~balustrade.codegen.runtime_grid`. :mod:`~balustrade.codegen.accelerate`: a
controller's step emitted, built (cached) and loaded in one call, for Python closed loops
at C speed.
The example targets and the ``balustrade codegen`` command live outside the package, in
:mod:`balustrade.examples.codegen` and :mod:`balustrade.examples.codegen_cli` (codegen imports
no models or designs).
"""

from balustrade.codegen.accelerate import accelerate
from balustrade.codegen.build import build, build_executable, find_compiler
from balustrade.codegen.emit import (
    Emitted,
    emit_approximate,
    emit_function,
    emit_functions,
    emit_pcbf,
    emit_problem,
    emit_problems,
    write_example,
)
from balustrade.codegen.emit_grid import emit_grid
from balustrade.codegen.emit_mo_lyap import emit_mo_lyapunov
from balustrade.codegen.emit_rapsf import emit_rapsf
from balustrade.codegen.emit_robust import emit_multiobjective, emit_robust
from balustrade.codegen.runtime import (
    CApproximatePCBFFilter,
    CFunction,
    CPCBFSafetyFilter,
    CProblem,
    load_manifest,
    mirror_c_retries,
)
from balustrade.codegen.runtime_grid import CGridPCBFFilter
from balustrade.codegen.runtime_mo_lyap import CMultiobjectiveLyapunovController
from balustrade.codegen.runtime_rapsf import CRAPSF
from balustrade.codegen.runtime_robust import CMultiobjectivePCBFFilter, CRobustPCBFSafetyFilter
from balustrade.codegen.support import SUPPORTED, check_no_callbacks, solver_libraries

__all__ = [
    "CRAPSF", "emit_rapsf", "CMultiobjectiveLyapunovController", "emit_mo_lyapunov",
    "SUPPORTED", "CApproximatePCBFFilter", "CFunction", "CPCBFSafetyFilter", "CProblem",
    "CMultiobjectivePCBFFilter", "CRobustPCBFSafetyFilter",
    "Emitted", "build", "build_executable", "check_no_callbacks", "emit_approximate",
    "emit_function", "emit_functions", "emit_pcbf", "emit_problem", "emit_problems",
    "emit_multiobjective", "emit_robust",
    "find_compiler",
    "load_manifest", "solver_libraries", "mirror_c_retries", "write_example",
    "CGridPCBFFilter", "emit_grid", "accelerate",
]
