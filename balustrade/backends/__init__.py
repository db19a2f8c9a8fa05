"""Backends: lower an :class:`~balustrade.dsl.ocp.OCP` to a solver, once.

``compile(ocp, target)`` returns an object with ``solve(params, warm_start=None) ->
Solution``; a target (:mod:`balustrade.backends.targets`) says which backend, solver,
options and retry chain. Synthesis problems (SDPs, :mod:`balustrade.dsl.synthesis`) are
lowered by ``compile_synthesis(problem, target="sdp")`` and solved to a ``SynthesisSolution``.
"""

from __future__ import annotations

from balustrade.backends.casadi_backend import CasadiCompiled
from balustrade.backends.cvxpy_backend import CvxpyCompiled
from balustrade.backends.daqp_engine import lowered_for_c
from balustrade.backends.direct_backend import DirectCompiled
from balustrade.backends.recovery import RECOVERY_TARGET, check_recovery_target, recovery_lead
from balustrade.backends.set_support import function_set_support
from balustrade.backends.solution import Solution, Status
from balustrade.backends.synthesis_cvxpy import (
    CompiledSynthesis,
    compile_synthesis,
    solve_synthesis,
)
from balustrade.backends.synthesis_solution import SynthesisSolution
from balustrade.backends.targets import PRESETS, Target, companion, sampling_targets
from balustrade.backends.targets import target as resolve_target
from balustrade.dsl.ocp import OCP
from balustrade.dsl.sets_function import register_support_solver
from balustrade.errors import BalustradeError, ConvexityError, SolverError

# FunctionSet.support needs an NLP; the language names no solver, the backends give it one
register_support_solver(function_set_support)

Compiled = CasadiCompiled | CvxpyCompiled | DirectCompiled

BACKENDS = {"casadi": CasadiCompiled, "cvxpy": CvxpyCompiled, "direct": DirectCompiled}


def compile(ocp: OCP, target: Target | str | None = None, solver: str | None = None,
            options: dict | None = None,
            retries: list[tuple[str, dict]] | None = None) -> Compiled:
    """Compile ``ocp`` for ``target``: a :class:`~balustrade.backends.targets.Target`, a
    preset name (:data:`~balustrade.backends.targets.PRESETS`) or a backend name
    (``"casadi"``: IPOPT; ``"cvxpy"``: PIQP for LPs/QPs, Clarabel for conic problems;
    ``"direct"``: the same solvers through their own interfaces, :mod:`.direct_backend`);
    ``None`` is ``"exact"``. ``solver``/``options``/``retries`` override the target's
    (see :func:`~balustrade.backends.targets.target`); ``retries`` (CasADi only) replaces
    the default retry chain after a failed solve (``[]`` turns retries off, e.g. for closed
    loops that have their own fallbacks). The returned object records ``.target``."""
    if not isinstance(ocp, OCP):
        raise BalustradeError(f"compile: expected a balustrade OCP, got {type(ocp).__name__}")
    if ocp.decision_vector().numel() == 0:
        raise BalustradeError(f"compile: {ocp.name} has no decision variables (declare them "
                              "with OCP(system, N) or ocp.variable)")
    if solver is not None and not isinstance(solver, str):
        raise SolverError(f"compile({ocp.name}): solver must be a name (str) or None, got "
                          f"{type(solver).__name__}")
    if options is not None and not isinstance(options, dict):
        raise SolverError(f"compile({ocp.name}): options must be a dict or None, got "
                          f"{type(options).__name__}")
    if retries is not None and not (isinstance(retries, list | tuple) and all(
            isinstance(r, tuple) and len(r) == 2 and isinstance(r[0], str)
            and isinstance(r[1], dict) for r in retries)):
        raise SolverError(f"compile({ocp.name}): retries must be a list of (solver name, "
                          f"options dict) pairs or None, got {retries!r:.60}")
    try:
        tgt = resolve_target(target, solver=solver, options=options, retries=retries)
    except SolverError as exc:
        raise SolverError(f"{ocp.name}: {exc}") from None
    if tgt.backend == "auto":
        return _compile_auto(ocp, tgt)
    if tgt.backend == "casadi":
        compiled: Compiled = CasadiCompiled(ocp, tgt.nlp_solver, tgt.solver_options(),
                                            tgt.retry_chain())
    elif tgt.backend == "direct":
        compiled = DirectCompiled(ocp, tgt.solver, tgt.solver_options())
    else:
        compiled = CvxpyCompiled(ocp, tgt.solver, tgt.solver_options())
    compiled.target = tgt
    return compiled


def _compile_auto(ocp: OCP, tgt: Target) -> Compiled:
    """The ``"auto"`` preset: the direct backend (``"fast-convex"``) when every block and
    cost term of ``ocp`` classifies as convex, else CasADi + IPOPT (``"exact"``); the
    target used is recorded as ``.target``."""
    if tgt.solver is not None or tgt.options:
        raise SolverError(f"{ocp.name}: the auto target picks its solver and takes no solver "
                          "or options; name a target ('fast-convex', 'exact') to tune one")
    try:
        compiled: Compiled = DirectCompiled(ocp)
        compiled.target = PRESETS["fast-convex"]
    except ConvexityError:
        exact = PRESETS["exact"]  # exactly what compile(ocp, "exact") builds
        compiled = CasadiCompiled(ocp, exact.nlp_solver, exact.solver_options(),
                                  exact.retry_chain())
        compiled.target = exact
    return compiled


__all__ = ["BACKENDS", "PRESETS", "CasadiCompiled", "Compiled", "CompiledSynthesis",
           "lowered_for_c",
           "recovery_lead", "RECOVERY_TARGET", "check_recovery_target",
           "CvxpyCompiled", "DirectCompiled", "Solution", "Status", "SynthesisSolution", "Target",
           "companion",
           "compile", "compile_synthesis", "resolve_target", "sampling_targets",
           "solve_synthesis"]
