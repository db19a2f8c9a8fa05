"""Regret-optimal synthesis (thesis Chapter 3): build the SDP, solve it, certify the controller.

The problems are stated in :mod:`balustrade.problems.regret.synthesis` (synthesis-language
SDPs that read like (3.19)–(3.41)); :func:`synthesize` lowers one through a target with the
structured pass of :mod:`balustrade.backends.synthesis_structured` (preset ``"sdp"`` by
default) and packs a :class:`SynthesisResult`: the
:class:`~balustrade.backends.synthesis_solution.SynthesisSolution` of the solve (its status is
one of the common statuses, its message says why), level, Φ_x, Φ_u, the causal controller
K = Φ_uΦ_x⁻¹ (3.15). Infeasible or failed solves — including a dense cone refused for memory
(status ``failed``, message "too large …") — return a status, never raise. The functions named
after the thesis problems (``dynamic_regret``, ``generalized_regret``, …) build and synthesize
in one call.

Every result carries a solver-independent certificate (:mod:`balustrade.problems.regret.verify`)
in ``info["certificate"]``: for the energy-bound and adversarial problems the exact worst-case
level of the returned controller, which is then the reported ``level`` (the SDP's own value is
``info["sdp_level"]``; the two agree to the solver's accuracy when the solve is accurate, and a
level is never reported below what its controller attains); for the pointwise problems
(3.32)/(3.34) a certified lower bound on the controller's worst case, which must not exceed the
level. ``res.ok`` means: the solver reports ``optimal`` (full accuracy) and the certificate
agrees. ``optimal_inaccurate`` is never ``ok`` — the solver's reduced tolerances were measured
to hide a level 33 % above the optimum in banded coordinates
(:mod:`balustrade.backends.lmi_banded`), and an "optimal" banded SCRW level 1.5e-5 below what
its controller attains — so a banded solve that is not ok is re-solved outside banded
coordinates (``lmi="split"``), the reason recorded in ``info["banded_fallback"]`` (or, when that
form cannot run, in ``info["banded_retry"]`` and the inaccurate result is returned with ``ok``
False). ``lmi="lifted"`` states an 𝒪 term through its LQ definition instead of whitening it
(:mod:`balustrade.problems.regret.lifting`; ``info["banded_route"]``): exact, not the default
(measured no better than the whitened form, and worse for (3.32) at T = 25, docs/regret.md).

``lmi`` chooses how the arrow LMIs reach the solver: ``"banded"`` (default), ``"split"``,
``"single"``, ``"lifted"`` (see :mod:`balustrade.backends.synthesis_structured`); ``target``
the solver (a :class:`~balustrade.backends.targets.Target` or preset name, default ``"sdp"``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from balustrade.backends.synthesis_solution import SUCCESS_STATUSES, SynthesisSolution
from balustrade.backends.synthesis_structured import compile_structured
from balustrade.backends.targets import Target
from balustrade.control.regret import RegretController
from balustrade.errors import BalustradeError
from balustrade.problems.regret.operators import Operators, controller_from_responses
from balustrade.problems.regret.synthesis import (
    RegretProblem,
    StateInputConstraints,
    adversarial_regret_problem,
    dynamic_regret_problem,
    generalized_regret_problem,
    h2_problem,
    hinf_problem,
    pointwise_dynamic_problem,
    pointwise_regret_problem,
    zero_x0_regret_problem,
)

TargetSpec = Target | str | None

# Relative slack of the certificate checks: the solver's tolerances (1e-8) with margin.
CERT_RTOL = 1e-6


@dataclass
class SynthesisResult:
    """Outcome of one synthesis: status, optimal level, responses Φ and controller K (3.15).

    ``status``/``message`` are those of ``solution`` (the common synthesis statuses);
    ``solve_time`` is the solver's own time, ``total_time`` building, solving and certifying.
    """

    name: str
    status: str
    level: float | None
    ops: Operators = field(repr=False)
    message: str = ""
    solution: SynthesisSolution | None = field(default=None, repr=False)
    Phi_x: np.ndarray | None = field(default=None, repr=False)
    Phi_u: np.ndarray | None = field(default=None, repr=False)
    K: np.ndarray | None = field(default=None, repr=False)
    solve_time: float = 0.0
    total_time: float = 0.0
    multipliers: dict = field(default_factory=dict, repr=False)
    info: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        """Solved to full accuracy (status "optimal") and the level agrees with its certificate.

        "optimal_inaccurate" is not ok: the solver met only its reduced tolerances, and on
        ill-conditioned SDPs (banded coordinates with the 𝒪 weight) that was measured to mean a
        level far from the optimum. Such a result keeps its controller and certificate for a
        caller that checks them itself (``controller(allow_inaccurate=True)``).
        """
        return (self.status == "optimal" and self.K is not None
                and self.info.get("certificate", {}).get("consistent", True))

    def gain(self, allow_inaccurate: bool = False) -> np.ndarray:
        """The causal gain K of (3.15) if usable (see :attr:`ok`; ``allow_inaccurate`` also
        accepts an ``optimal_inaccurate`` result with a gain)."""
        usable = self.ok or (allow_inaccurate and self.status in SUCCESS_STATUSES
                             and self.K is not None)
        if not usable:
            raise BalustradeError(f"{self.name}: no controller, synthesis status {self.status!r}"
                                  + (f" ({self.message})" if self.message else "")
                                  + ("" if self.K is None else " (not certified, see .ok)"))
        return self.K

    def controller(self, allow_inaccurate: bool = False) -> RegretController:
        """The closed-loop controller of this result
        (:meth:`~balustrade.control.regret.RegretController.from_result`)."""
        return RegretController.from_result(self, allow_inaccurate)


def _attach_certificate(res: SynthesisResult, kind: str, value: float) -> None:
    """The SDP's level must bound what its own controller attains: consistent when the exact
    level ("exact") or the certified lower bound ("lower_bound") does not exceed it beyond
    CERT_RTOL. An exact level becomes the reported level (the SDP value stays in
    info["sdp_level"]): it is what the returned controller guarantees."""
    sdp = float(res.level)   # type: ignore[arg-type]
    cert = {"kind": kind, "value": float(value), "sdp_level": sdp,
            "consistent": bool(value <= sdp + CERT_RTOL * max(abs(sdp), 1e-12))}
    if kind == "exact":
        res.level = float(value)
    res.info["certificate"] = cert
    res.info["sdp_level"] = sdp


def solve_once(problem: RegretProblem, lmi: str = "banded", target: TargetSpec = None
               ) -> SynthesisResult:
    """Solve ``problem`` with its LMI in the form ``lmi`` (no re-solve) and certify the result."""
    t0 = time.perf_counter()
    sol = compile_structured(problem.sdp, target, lmi).solve()
    ops = problem.ops
    info = {"n_theta": problem.par.n_theta, **sol.info}
    res = SynthesisResult(problem.name, sol.status, None, ops, message=sol.message,
                          solution=sol, solve_time=_solver_time(sol),
                          total_time=time.perf_counter() - t0, info=info)
    if sol.ok:
        v = sol.values
        Phi_u = problem.par.phi_u_value(v["theta"])
        Phi_x = ops.phi_x(Phi_u)
        res.Phi_u, res.Phi_x = Phi_u, Phi_x
        res.K = controller_from_responses(ops, Phi_x, Phi_u)
        res.level = problem.level(v)
        res.multipliers = {name: v[name] for name in problem.multipliers}
        if problem.certify is not None:
            _attach_certificate(res, *problem.certify(Phi_u, v))
        res.total_time = time.perf_counter() - t0
    return res


def _solver_time(sol: SynthesisSolution) -> float:
    return sol.solver_time if np.isfinite(sol.solver_time) else sol.solve_time


def synthesize(problem: RegretProblem, lmi: str = "banded", target: TargetSpec = None
               ) -> SynthesisResult:
    """Solve and certify; a banded solve that is not ok (not "optimal", or its level below what
    its own controller attains: both measured with the 𝒪 weight, lmi_banded.py) is re-solved in
    the form used when banded coordinates do not apply (``lmi="split"``: the chordal split, or
    one dense cone where no split exists, refused — status "failed", message "too large …" —
    when it would not fit in memory). The retry is returned when it is ok, with the banded
    attempt in info["banded_fallback"]; otherwise the banded result is returned with the
    retry's outcome in info["banded_retry"]."""
    res = solve_once(problem, lmi, target)
    if res.info.get("lmi") != "banded" or res.ok:   # "lifted" is reported as "banded"
        return res
    retry = solve_once(problem, "split", target)
    cert = res.info.get("certificate", {})
    why = (f"certificate {cert.get('kind')} {cert.get('value')} above the SDP level "
           f"{cert.get('sdp_level')}" if not cert.get("consistent", True) else "")
    attempt = (f"banded solve ended {res.status!r} (level {res.level}"
               + (f"; {why}" if why else "") + f", {res.total_time:.1f} s); "
               "re-solved with lmi='split'")
    if retry.ok:
        retry.info["banded_fallback"] = attempt
        retry.total_time += res.total_time
        return retry
    res.info["banded_retry"] = {"status": retry.status, "level": retry.level,
                                "message": retry.message}
    res.total_time += retry.total_time
    return res


# ----------------------------------------------------------------------------------------------
# the thesis problems, built and synthesized in one call
# ----------------------------------------------------------------------------------------------
def dynamic_regret(ops: Operators, x0: object, omega: float, *,
                   constraints: StateInputConstraints | None = None,
                   constraint_P: object | None = None, lmi: str = "banded",
                   target: TargetSpec = None) -> SynthesisResult:
    """(3.19), see :func:`~balustrade.problems.regret.synthesis.dynamic_regret_problem`."""
    return synthesize(dynamic_regret_problem(ops, x0, omega, constraints=constraints,
                                             constraint_P=constraint_P), lmi, target)


def adversarial_regret(ops: Operators, *, constraints: StateInputConstraints | None = None,
                       x0: object | None = None, constraint_P: object | None = None,
                       omega: float | None = None, lmi: str = "banded",
                       target: TargetSpec = None) -> SynthesisResult:
    """(3.24), see :func:`~balustrade.problems.regret.synthesis.adversarial_regret_problem`."""
    return synthesize(adversarial_regret_problem(ops, constraints=constraints, x0=x0,
                                                 constraint_P=constraint_P, omega=omega),
                      lmi, target)


def generalized_regret(ops: Operators, x0: object, omega: float, W: object = "I", *,
                       constraints: StateInputConstraints | None = None,
                       constraint_P: object | None = None, lmi: str = "banded",
                       target: TargetSpec = None) -> SynthesisResult:
    """(3.28), see :func:`~balustrade.problems.regret.synthesis.generalized_regret_problem`."""
    return synthesize(generalized_regret_problem(ops, x0, omega, W, constraints=constraints,
                                                 constraint_P=constraint_P), lmi, target)


def zero_x0_regret(ops: Operators, W: object = "I", *, adversarial_x0: bool = False,
                   constraints: StateInputConstraints | None = None,
                   constraint_P: object | None = None, omega: float | None = None,
                   lmi: str = "banded", target: TargetSpec = None) -> SynthesisResult:
    """(3.30), see :func:`~balustrade.problems.regret.synthesis.zero_x0_regret_problem`."""
    return synthesize(zero_x0_regret_problem(ops, W, adversarial_x0=adversarial_x0,
                                             constraints=constraints,
                                             constraint_P=constraint_P, omega=omega),
                      lmi, target)


def pointwise_regret(ops: Operators, x0: object, P: object, W: object = "I", *,
                     constraints: StateInputConstraints | None = None, lmi: str = "banded",
                     target: TargetSpec = None) -> SynthesisResult:
    """(3.32), see :func:`~balustrade.problems.regret.synthesis.pointwise_regret_problem`."""
    return synthesize(pointwise_regret_problem(ops, x0, P, W, constraints=constraints),
                      lmi, target)


def pointwise_dynamic_regret(ops: Operators, x0: object, P: object, *,
                             constraints: StateInputConstraints | None = None,
                             lmi: str = "banded", target: TargetSpec = None
                             ) -> SynthesisResult:
    """(3.34), see :func:`~balustrade.problems.regret.synthesis.pointwise_dynamic_problem`."""
    return synthesize(pointwise_dynamic_problem(ops, x0, P, constraints=constraints),
                      lmi, target)


def h2(ops: Operators, x0: object, *, constraints: StateInputConstraints | None = None,
       constraint_P: object | None = None, omega: float | None = None,
       target: TargetSpec = None) -> SynthesisResult:
    """SH2, see :func:`~balustrade.problems.regret.synthesis.h2_problem` (no LMI)."""
    return solve_once(h2_problem(ops, x0, constraints=constraints, constraint_P=constraint_P,
                                 omega=omega), "split", target)


def hinf(ops: Operators, *, x0: object | None = None,
         constraints: StateInputConstraints | None = None, constraint_P: object | None = None,
         omega: float | None = None, lmi: str = "banded", target: TargetSpec = None
         ) -> SynthesisResult:
    """SH∞, see :func:`~balustrade.problems.regret.synthesis.hinf_problem`."""
    return synthesize(hinf_problem(ops, x0=x0, constraints=constraints,
                                   constraint_P=constraint_P, omega=omega), lmi, target)


__all__ = ["CERT_RTOL", "SynthesisResult", "adversarial_regret", "dynamic_regret",
           "generalized_regret", "h2", "hinf", "pointwise_dynamic_regret", "pointwise_regret",
           "solve_once", "synthesize", "zero_x0_regret"]
