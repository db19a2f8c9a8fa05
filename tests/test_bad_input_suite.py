"""The bad-input suite: every public entry point × wrong shapes, NaN/inf, empty sets,
non-PSD weights, wrong types, missing names and extreme magnitudes.

Each case ends in one of

* ``error``  — a :class:`~balustrade.errors.BalustradeError` (whose message names the
  argument, where the case says what to look for);
* ``status`` — a solve that returned an honest non-usable status;
* ``ok``     — the input was valid and the result is sound (a usable solution passes
  :func:`balustrade.verify`, numbers are finite);

and never in ``raw`` (any other exception) or ``bad`` (a usable result with NaN or one that
fails ``verify``). Cases that run a solver on extreme data run in a subprocess, so that a
crash inside CasADi or a solver is reported instead of killing the test run.

``python tests/test_bad_input_suite.py`` runs every case and prints the tally; under pytest
the last test prints it (``-s``) and checks that no case was raw.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import balustrade
from balustrade.backends import Solution, compile
from balustrade.control.base import StepInfo, Trace, simulate
from balustrade.control.pcbf import PCBFSafetyFilter
from balustrade.control.robust_steps import slack_cost
from balustrade.design.terminal_cbf import synthesize_terminal_cbf
from balustrade.dsl import (
    OCP,
    Box,
    Cost,
    Ellipsoid,
    FunctionSet,
    LinearSystem,
    Polytope,
    System,
    norm,
    quad,
    squared_norm,
    sum_norms,
)
from balustrade.dsl.error_sets import (
    ErrorSet,
    is_rpi,
    reachable_support,
    reachable_tightened_sets,
    tighten,
    tighten_by_feedback,
)
from balustrade.errors import BalustradeError
from balustrade.problems.approximate import approximate_filter_problem, max_decrease_problem
from balustrade.problems.mpc import (
    cbf_filter_problem,
    mpc_problem,
    predictive_safety_filter,
    soft_mpc_problem,
)
from balustrade.problems.multiobjective import (
    decrease_bound,
    multiobjective_lyapunov_problem,
    multiobjective_pcbf_problem,
)
from balustrade.problems.pcbf import (
    combined_h,
    extended_pcbf_problem,
    pcbf_filter_problem,
    pcbf_slack_problem,
)
from balustrade.problems.robust import (
    robust_mpc_problem,
    robust_pcbf_filter_problem,
    robust_pcbf_slack_problem,
    tube_mpc_problem,
)
from balustrade.testing import verify

# -- a small, fast model ------------------------------------------------------------------------
A = np.array([[1.0, 0.1], [0.0, 1.0]])
B = np.array([[0.0], [0.1]])
SYS = LinearSystem(A, B, name="double_integrator")
X = Box([-1.0, -1.0], [1.0, 1.0], name="X")
U = Box([-1.0], [1.0], name="U")
N = 3
DELTAS = np.zeros(N)  # untightened: equal steps warn (TighteningWarning), filtered below
pytestmark = pytest.mark.filterwarnings("ignore::balustrade.errors.TighteningWarning")
ERROR = ErrorSet(Ellipsoid(np.eye(2) * 400.0, name="E"), np.array([[-1.0, -1.5]]))


def h_f(x: ca.SX) -> ca.SX:
    return ca.sumsqr(x) - 0.1


def _slack(**kw: object) -> OCP:
    args = {"system": SYS, "X": X, "U": U, "h_f": h_f, "N": N, "deltas": DELTAS, **kw}
    return pcbf_slack_problem(**args)


_COMPILED: dict[str, object] = {}


def compiled(backend: str = "cvxpy"):
    """The (2.24) problem of the small model, compiled once per backend."""
    if backend not in _COMPILED:
        ocp = _slack(alpha_f=1e3, slack_norm=1)
        _COMPILED[backend] = (ocp, compile(ocp, backend, "sqpmethod" if backend == "casadi"
                                           else None))
    return _COMPILED[backend]


def solved(backend: str = "cvxpy", x0: object = (0.1, 0.0)) -> tuple[OCP, Solution]:
    ocp, c = compiled(backend)
    return ocp, c.solve({"x0": x0})


# -- the case registry --------------------------------------------------------------------------
@dataclass
class Case:
    name: str
    run: Callable[[], object]
    expect: str = "error"       # "error": must raise a BalustradeError; "any": error/status/ok
    match: str | None = None    # what the error message must name
    risky: bool = False         # runs a solver on extreme data: subprocess


CASES: dict[str, Case] = {}
TALLY: Counter = Counter()


def case(name: str, expect: str = "error", match: str | None = None, risky: bool = False):
    def register(fn: Callable[[], object]) -> Callable[[], object]:
        assert name not in CASES, name
        CASES[name] = Case(name, fn, expect, match, risky)
        return fn
    return register


def many(prefix: str, thunks: dict[str, Callable[[], object]], expect: str = "error",
         match: str | None = None) -> None:
    for key, fn in thunks.items():
        case(f"{prefix}:{key}", expect, match)(fn)


def judge(result: object) -> tuple[str, str]:
    """Classify a returned value (see the module docstring)."""
    if isinstance(result, tuple) and len(result) == 2 and isinstance(result[1], Solution):
        ocp, sol = result
        if not sol.usable:
            return "status", sol.status
        if not np.all(np.isfinite(sol.w)) or not np.isfinite(sol.objective):
            return "bad", f"usable ({sol.status}) with NaN"
        scale = max(1.0, float(np.max(np.abs(sol.w), initial=0.0)))
        report = verify(ocp, sol, tol=1e-6 * scale)
        return ("ok", sol.status) if report.ok else ("bad", str(report))
    if isinstance(result, Solution):
        raise AssertionError("a case returned a bare Solution: return (ocp, solution)")
    if isinstance(result, Trace):
        finite = np.all(np.isfinite(result.states)) or result.stopped
        return ("ok", "trace") if finite else ("bad", "trace with NaN and no stop reason")
    if isinstance(result, (float, np.ndarray)) and not np.all(np.isfinite(result)):
        return "bad", f"non-finite number {result}"
    return "ok", type(result).__name__


def classify(fn: Callable[[], object]) -> tuple[str, str]:
    try:
        result = fn()
    except BalustradeError as exc:
        return "error", f"{type(exc).__name__}: {exc}"
    except Exception as exc:  # noqa: BLE001 - exactly what the suite hunts
        return "raw", f"{type(exc).__name__}: {exc}"
    return judge(result)


def check_case(c: Case, outcome: str, detail: str) -> None:
    TALLY["cases"] += 1
    TALLY[outcome] += 1
    assert outcome not in ("raw", "bad"), f"{c.name}: {outcome}: {detail}"
    if c.expect == "error":
        assert outcome == "error", f"{c.name}: expected a BalustradeError, got {outcome} " \
                                   f"({detail})"
    if outcome == "error" and c.match is not None:
        assert c.match.lower() in detail.lower(), f"{c.name}: message does not name " \
                                                  f"{c.match!r}: {detail}"
    if outcome == "error":
        assert len(detail.split(": ", 1)[-1]) > 10, f"{c.name}: uninformative: {detail}"


# -- systems ----------------------------------------------------------------------------------
def _dyn(g: Callable) -> Callable:
    return lambda: System(lambda x, u: ca.vertcat(x[0] + 0.1 * x[1], g(x) + u), 2, 1,
                          name="pendulum")


many("System: symbol lost", {
    "math.sin": _dyn(lambda x: math.sin(x[0])),
    "math.cos": _dyn(lambda x: math.cos(x[0])),
    "math.exp": _dyn(lambda x: math.exp(x[1])),
    "float()": _dyn(lambda x: float(x[0])),
    "np.asarray(float)": _dyn(lambda x: np.asarray(x[0], dtype=float)),
    "int()": _dyn(lambda x: int(x[0])),
    "math.sqrt": _dyn(lambda x: math.sqrt(x[0])),
    "continuous math.sin": lambda: System.from_continuous(
        lambda x, u: ca.vertcat(x[1], -math.sin(x[0]) + u), 2, 1, 0.1, name="pendulum"),
}, match="pendulum")
case("System: symbol lost message names ca.sin", match="ca.sin")(_dyn(lambda x: math.sin(x[0])))
case("System: np.sin works on symbols", expect="any")(_dyn(lambda x: np.sin(x[0])))


@case("System.from_sympy: function without CasADi counterpart", match="from_sympy")
def _sympy_unsupported():
    import sympy

    x1, x2, u = sympy.symbols("x1 x2 u")
    return System.from_sympy([x1 + x2, sympy.gamma(x1) + u], [x1, x2], [u], name="sym")


many("System: arguments", {
    "nx=0": lambda: System(lambda x, u: x, 0, 1),
    "nx=-1": lambda: System(lambda x, u: x, -1, 1),
    "nx=2.5": lambda: System(lambda x, u: x, 2.5, 1),
    "nx='2'": lambda: System(lambda x, u: x, "2", 1),
    "nu=-1": lambda: System(lambda x, u: x, 2, -1),
    "f not callable": lambda: System("x + u", 2, 1),
    "f wrong size": lambda: System(lambda x, u: x[0] + u, 2, 1),
    "f returns str": lambda: System(lambda x, u: "x", 2, 1),
    "f raises": lambda: System(lambda x, u: x @ np.ones((3, 3)), 2, 1),
    "name=3": lambda: System(lambda x, u: x, 2, 1, name=3),
    "steps=0": lambda: System.from_continuous(lambda x, u: -x + u, 1, 1, 0.1, steps=0),
    "steps=1.5": lambda: System.from_continuous(lambda x, u: -x + u, 1, 1, 0.1, steps=1.5),
    "dt=0": lambda: System.from_continuous(lambda x, u: -x + u, 1, 1, 0.0),
    "dt=nan": lambda: System.from_continuous(lambda x, u: -x + u, 1, 1, float("nan")),
    "dt='0.1'": lambda: System.from_continuous(lambda x, u: -x + u, 1, 1, "0.1"),
    "method=rk5": lambda: System.from_continuous(lambda x, u: -x + u, 1, 1, 0.1, "rk5"),
})
many("LinearSystem", {
    "A='abc'": lambda: LinearSystem("abc", [[1.0]]),
    "B='ab'": lambda: LinearSystem(np.eye(2), "ab"),
    "A=None": lambda: LinearSystem(None, [[1.0]]),
    "A ragged": lambda: LinearSystem([[1.0, 2.0], [3.0]], [[1.0], [1.0]]),
    "A complex": lambda: LinearSystem(np.eye(2) * 1j, np.ones((2, 1))),
    "A NaN": lambda: LinearSystem([[np.nan]], [[1.0]]),
    "A inf": lambda: LinearSystem([[np.inf]], [[1.0]]),
    "A not square": lambda: LinearSystem(np.ones((2, 3)), np.ones((2, 1))),
    "A empty": lambda: LinearSystem([], [[1.0]]),
    "B wrong rows": lambda: LinearSystem(np.eye(2), np.ones((3, 1))),
    "E wrong rows": lambda: LinearSystem(np.eye(2), np.ones((2, 1)), np.ones((3, 2))),
    "A of SX": lambda: LinearSystem([[ca.SX.sym("a")]], [[1.0]]),
}, match="")
case("LinearSystem: extreme magnitude accepted", expect="any")(
    lambda: LinearSystem([[1e300]], [[1e-300]]).step([1.0], [0.0]))
many("System.step", {
    "x NaN": lambda: SYS.step([np.nan, 0.0], [0.0]),
    "x wrong size": lambda: SYS.step([0.0, 0.0, 0.0], [0.0]),
    "x string": lambda: SYS.step("ab", [0.0]),
    "u inf": lambda: SYS.step([0.0, 0.0], [np.inf]),
    "jacobians wrong size": lambda: SYS.jacobians([0.0], [0.0]),
}, match="double_integrator")

# -- sets ---------------------------------------------------------------------------------------
many("Box", {
    "empty dims": lambda: Box([], []),
    "lb > ub": lambda: Box([1.0], [0.0]),
    "NaN": lambda: Box([np.nan], [1.0]),
    "strings": lambda: Box("a", "b"),
    "sizes differ": lambda: Box([0.0, 0.0], [1.0]),
    "lb = +inf": lambda: Box([np.inf], [np.inf]),
    "symmetric negative": lambda: Box.symmetric(-1.0, dim=2),
    "symmetric wrong dim": lambda: Box.symmetric([1.0, 2.0], dim=3),
    "symmetric dim=0": lambda: Box.symmetric(1.0, dim=0),
    "name=None": lambda: Box([0.0], [1.0], name=None),
})
many("Polytope", {
    "no columns": lambda: Polytope(np.zeros((2, 0)), [1.0, 1.0]),
    "H NaN": lambda: Polytope([[np.nan, 1.0]], [1.0]),
    "h inf": lambda: Polytope(np.eye(2), [np.inf, 1.0]),
    "h wrong size": lambda: Polytope(np.eye(2), np.ones(3)),
    "empty set": lambda: Polytope(np.array([[1.0], [-1.0]]), np.array([-1.0, 0.0])),
    "H string": lambda: Polytope("H", [1.0]),
    "H 3-D": lambda: Polytope(np.ones((2, 2, 2)), [1.0, 1.0]),
})
many("Ellipsoid", {
    "not PSD": lambda: Ellipsoid(np.array([[1.0, 2.0], [2.0, 1.0]])),
    "zero": lambda: Ellipsoid(np.zeros((2, 2))),
    "NaN": lambda: Ellipsoid([[np.nan]]),
    "not square": lambda: Ellipsoid(np.ones((2, 3))),
    "not symmetric": lambda: Ellipsoid(np.array([[1.0, 0.5], [0.0, 1.0]])),
    "center wrong size": lambda: Ellipsoid(np.eye(2), center=[0.0]),
    "center inf": lambda: Ellipsoid(np.eye(2), center=[np.inf, 0.0]),
    "P string": lambda: Ellipsoid("P"),
    "empty": lambda: Ellipsoid([]),
})
many("FunctionSet", {
    "dim=0": lambda: FunctionSet(lambda x: x, dim=0),
    "dim=-1": lambda: FunctionSet(lambda x: x, dim=-1),
    "dim=1.5": lambda: FunctionSet(lambda x: x, dim=1.5),
    "c not callable": lambda: FunctionSet("x <= 1", dim=2),
    "c math.sin": lambda: FunctionSet(lambda x: math.sin(x[0]) - 0.5, dim=2, name="ring"),
    "c matrix": lambda: FunctionSet(lambda x: x @ x.T, dim=2),
    "c raises": lambda: FunctionSet(lambda x: x[5], dim=2),
    "c empty": lambda: FunctionSet(lambda x: ca.SX(0, 1), dim=2),
    "c string": lambda: FunctionSet(lambda x: "x", dim=2),
})
many("set operations", {
    "scale NaN": lambda: X.scale(float("nan")),
    "scale string": lambda: X.scale("2"),
    "Ellipsoid scale 0": lambda: Ellipsoid(np.eye(2)).scale(0.0),
    "translate wrong size": lambda: X.translate([1.0]),
    "translate NaN": lambda: Ellipsoid(np.eye(2)).translate([np.nan, 0.0]),
    "contains wrong size": lambda: X.contains([0.0]),
    "contains NaN": lambda: X.contains([np.nan, 0.0]),
    "contains_many wrong columns": lambda: X.contains_many(np.zeros((3, 3))),
    "contains_many string": lambda: X.contains_many("ab"),
    "support wrong size": lambda: X.support([1.0]),
    "support NaN": lambda: Ellipsoid(np.eye(2)).support([np.nan, 1.0]),
    "sample -1": lambda: X.sample(-1),
    "sample 2.5": lambda: X.sample(2.5),
    "sample rng string": lambda: X.sample(3, rng="seed"),
    "tighten wrong dim": lambda: X.tighten(U),
    "tighten not a set": lambda: X.tighten("E"),
    "tighten to empty": lambda: X.tighten(Box.symmetric(2.0, dim=2)),
    "tighten by unbounded": lambda: Polytope(np.eye(2), np.ones(2)).tighten(
        Box([-np.inf, 0.0], [np.inf, 0.0])),
    "linear_map wrong shape": lambda: X.linear_map(np.eye(3)),
    "linear_map NaN": lambda: X.linear_map(np.full((2, 2), np.nan)),
    "ellipsoid map rank deficient": lambda: Ellipsoid(np.eye(2)).linear_map(np.zeros((2, 2))),
    "minkowski wrong dim": lambda: X.minkowski_sum(U),
    "subset tol NaN": lambda: X.is_subset_of(Ellipsoid(np.eye(2)), tol=np.nan),
    "subset not a set": lambda: X.is_subset_of("X"),
    "contains tol string": lambda: X.contains([0.0, 0.0], tol="a"),
    "contains_many tol NaN": lambda: Ellipsoid(np.eye(2)).contains_many(np.zeros((1, 2)),
                                                                        tol=np.nan),
    "c of a list": lambda: Ellipsoid(np.eye(2)).c([1.0, 2.0]),
    "max_quadratic_over a string": lambda: Ellipsoid(np.eye(2)).max_quadratic_over("E"),
    "sample 10^12 points": lambda: X.sample(10**12),
    "sample a box too wide for floats": lambda: Box([-1e308], [1e308]).sample(2),
    "sample unbounded box": lambda: Box([-np.inf], [1.0]).sample(2),
    "FunctionSet sample without bounds": lambda: FunctionSet(lambda x: ca.sumsqr(x) - 1,
                                                             2).sample(3),
    "ErrorSet E not a set": lambda: ErrorSet("E", None),
    "ErrorSet K wrong columns": lambda: ErrorSet(Ellipsoid(np.eye(2)), np.ones((1, 3))),
    "reachable_support N=-1": lambda: reachable_support(A, X, np.eye(2), -1),
    "reachable_support A not square": lambda: reachable_support(np.ones((2, 3)), X,
                                                                np.eye(2), 2),
})

# -- the OCP builder ----------------------------------------------------------------------------


def _ocp() -> OCP:
    o = OCP(SYS, N, name="bad")
    o.initial_state(o.parameter("x0", 2))
    o.dynamics()
    return o


many("OCP", {
    "N=0": lambda: OCP(SYS, 0),
    "N=1.5": lambda: OCP(SYS, 1.5),
    "N='3'": lambda: OCP(SYS, "3"),
    "N=True": lambda: OCP(SYS, True),
    "system string": lambda: OCP("system", 3),
    "name=None": lambda: OCP(SYS, 3, name=None),
    "parameter rows=-1": lambda: OCP().parameter("p", -1),
    "parameter cols='a'": lambda: OCP().parameter("p", 1, "a"),
    "parameter name=3": lambda: OCP().parameter(3, 1),
    "parameter name not identifier": lambda: OCP().parameter("x 0", 1),
    "parameter value wrong shape": lambda: OCP().parameter("p", 2, value=[1.0, 2.0, 3.0]),
    "parameter value NaN": lambda: OCP().parameter("p", 1, value=np.nan),
    "parameter value string": lambda: OCP().parameter("p", 1, value="one"),
    "variable rows=-1": lambda: OCP().variable("v", -1),
    "variable lb NaN": lambda: OCP().variable("v", 2, lb=np.nan),
    "variable lb > ub": lambda: OCP().variable("v", 2, lb=1.0, ub=0.0),
    "variable init inf": lambda: OCP().variable("v", 2, init=np.inf),
    "variable duplicate": lambda: _ocp().variable("x", 1),
    "initial_state wrong size": lambda: OCP(SYS, 2).initial_state([0.0]),
    "initial_state NaN": lambda: OCP(SYS, 2).initial_state([np.nan, 0.0]),
    "dynamics w wrong size": lambda: OCP(SYS, 2).dynamics(w=[1.0]),
    "tightening NaN": lambda: _ocp().state_constraint(X, tightening=np.nan),
    "tightening vector with NaN": lambda: _ocp().state_constraint(X, tightening=[0, np.nan,
                                                                                 0]),
    "tightening wrong length": lambda: _ocp().state_constraint(X, tightening=[0.0, 0.1]),
    "tightening callable NaN": lambda: _ocp().state_constraint(X, tightening=lambda i: np.nan),
    "tightening string": lambda: _ocp().state_constraint(X, tightening="0.1"),
    # a negative Δ_i relaxes a hard row beyond the declared set (audit B, session 14)
    "tightening negative": lambda: _ocp().state_constraint(X, tightening=-0.1),
    "tightening vector negative": lambda: _ocp().state_constraint(X, tightening=[0, -0.1, 0]),
    "tightening callable negative": lambda: _ocp().state_constraint(X, tightening=lambda i: -i),
    "input tightening negative": lambda: _ocp().input_constraint(U, tightening=-0.1),
    "steps out of range": lambda: _ocp().state_constraint(X, steps=[0, 7]),
    "steps negative": lambda: _ocp().state_constraint(X, steps=[-1]),
    # u has N columns: step N was a raw CasADi slice error (audit B, session 14)
    "input steps = N": lambda: _ocp().input_constraint(U, steps=[N]),
    "steps string": lambda: _ocp().state_constraint(X, steps="01"),
    "steps float": lambda: _ocp().input_constraint(U, steps=[0.5]),
    "steps empty": lambda: _ocp().input_constraint(U, steps=[]),
    "set wrong dim": lambda: _ocp().state_constraint(U),
    "set not a set": lambda: _ocp().state_constraint("X"),
    "sets per step wrong count": lambda: _ocp().state_constraint([X, X]),
    "slack unknown string": lambda: _ocp().state_constraint(X, slack="free"),
    "slack wrong shape": lambda: _ocp().state_constraint(X, slack=ca.SX.sym("s", 2, 2)),
    "terminal tightening NaN": lambda: _ocp().terminal_constraint(X, tightening=np.nan),
    "terminal tightening negative": lambda: _ocp().terminal_constraint(X, tightening=-0.1),
    "terminal_cbf not callable": lambda: _ocp().terminal_cbf("h_f"),
    "terminal_cbf math.sin": lambda: _ocp().terminal_cbf(lambda x: math.sin(x[0])),
    "terminal_cbf vector": lambda: _ocp().terminal_cbf(lambda x: x),
    "le with NaN constant": lambda: _ocp().le(_ocp().x[0, 0], np.nan),
    "le with string": lambda: _ocp().le("x", 0),
    "eq mismatched shapes": lambda: _ocp().eq(ca.SX.sym("a", 3), ca.SX.sym("b", 2)),
    "block name=None": lambda: _ocp().le(1.0, 2.0, name=None),
    "minimize string": lambda: _ocp().minimize("cost"),
    "minimize NaN": lambda: _ocp().minimize(float("nan")),
    "minimize vector": lambda: _ocp().minimize(ca.SX.sym("v", 2)),
    "minimize NaN weight": lambda: _ocp().minimize(ca.SX.sym("v") * np.nan),
    "need system": lambda: OCP().dynamics(),
    "unpack wrong size": lambda: _ocp().unpack_variables(np.zeros(3)),
    "pack unknown name": lambda: _ocp().pack_variables({"y": 1.0}),
    "pack list": lambda: _ocp().pack_variables([1.0]),
})
many("costs", {
    "-squared_norm": lambda: -squared_norm(ca.SX.sym("a", 2)),
    "-norm": lambda: -norm(ca.SX.sym("a", 2), 1),
    "0 - norm": lambda: 0.0 - norm(ca.SX.sym("a", 2), 1),
    "norm order 3": lambda: norm(ca.SX.sym("a", 2), 3),
    "norm order array": lambda: norm(ca.SX.sym("a", 2), np.array([1, 2])),
    "norm of string": lambda: norm("abc"),
    "norm of NaN": lambda: norm([np.nan, 1.0]),
    "norm math.sin": lambda: norm(math.sin(ca.SX.sym("a"))),
    "quad non-PSD": lambda: quad(ca.SX.sym("a", 2), -np.eye(2)),
    "quad Q wrong shape": lambda: quad(ca.SX.sym("a", 2), np.eye(3)),
    "quad Q NaN": lambda: quad(ca.SX.sym("a", 2), np.full((2, 2), np.nan)),
    "quad Q string": lambda: quad(ca.SX.sym("a", 2), "I"),
    "cost * NaN": lambda: squared_norm(ca.SX.sym("a")) * float("nan"),
    "cost * string": lambda: squared_norm(ca.SX.sym("a")) * "2",
    "cost * symbol": lambda: norm(ca.SX.sym("a")) * ca.SX.sym("w"),
    "Cost.of list": lambda: Cost.of([1.0]),
    "Cost.of inf": lambda: Cost.of(float("inf")),
    "sum_norms numpy": lambda: sum_norms(np.ones((2, 2))),
})
case("costs: -(smooth) is allowed", expect="any")(lambda: -Cost.of(ca.SX.sym("a") ** 2))

# -- formulation builders -----------------------------------------------------------------------
many("pcbf_slack_problem", {
    "alpha_f=-1": lambda: _slack(alpha_f=-1.0),
    "alpha_f=0": lambda: _slack(alpha_f=0.0),
    "alpha_f=NaN": lambda: _slack(alpha_f=float("nan")),
    "alpha_f=inf": lambda: _slack(alpha_f=float("inf")),
    "alpha_f string": lambda: _slack(alpha_f="1e6"),
}, match="alpha_f")
many("pcbf_slack_problem", {
    "deltas NaN": lambda: _slack(deltas=[0.0, np.nan, 0.0]),
    "deltas negative": lambda: _slack(deltas=[0.0, -0.1, 0.0]),
    "deltas short": lambda: _slack(deltas=[0.0, 0.1]),
    "deltas inf": lambda: _slack(deltas=np.full(N, np.inf)),
    "deltas string": lambda: _slack(deltas="0"),
}, match="deltas")
many("pcbf_slack_problem", {
    "N=0": lambda: _slack(N=0, deltas=[]),
    "N=2.5": lambda: _slack(N=2.5),
}, match="horizon N")
many("pcbf builders", {
    "slack_norm=3": lambda: _slack(slack_norm=3),
    "h_f not callable": lambda: _slack(h_f=0.5),
    "h_f math.cos": lambda: _slack(h_f=lambda x: math.cos(x[0])),
    "X wrong dim": lambda: _slack(X=U),
    "U not a set": lambda: _slack(U=[-1, 1]),
    "system not a System": lambda: _slack(system=A),
    "filter eps<0": lambda: pcbf_filter_problem(SYS, X, U, h_f, N, DELTAS, eps=-1e-3),
    "filter eps NaN": lambda: pcbf_filter_problem(SYS, X, U, h_f, N, DELTAS, eps=np.nan),
    "extended deltas NaN": lambda: extended_pcbf_problem(SYS, X, U, h_f, N, [np.nan] * N),
    "combined_h NaN": lambda: combined_h(float("nan"), 0.0),
    "combined_h c_h<0": lambda: combined_h(0.0, -1.0, c_h=-1.0),
})
many("mpc builders", {
    "Q not PSD": lambda: mpc_problem(SYS, X, U, None, N, -np.eye(2), np.eye(1), np.eye(2)),
    "Q wrong shape": lambda: mpc_problem(SYS, X, U, None, N, np.eye(3), np.eye(1), np.eye(2)),
    "R NaN": lambda: mpc_problem(SYS, X, U, None, N, np.eye(2), [[np.nan]], np.eye(2)),
    "P string": lambda: mpc_problem(SYS, X, U, None, N, np.eye(2), np.eye(1), "P"),
    "Xf wrong dim": lambda: mpc_problem(SYS, X, U, U, N, np.eye(2), np.eye(1), np.eye(2)),
    "soft penalty<0": lambda: soft_mpc_problem(SYS, X, U, None, N, np.eye(2), np.eye(1),
                                               np.eye(2), penalty=-1.0),
    "soft slack_norm": lambda: soft_mpc_problem(SYS, X, U, None, N, np.eye(2), np.eye(1),
                                                np.eye(2), slack_norm=0),
})
many("robust builders", {
    "deltas NaN": lambda: robust_pcbf_slack_problem(SYS, X, U, h_f, N, [np.nan] * N, ERROR),
    "alpha_f<0": lambda: robust_pcbf_slack_problem(SYS, X, U, h_f, N, DELTAS, ERROR,
                                                   alpha_f=-1.0),
    "error not an ErrorSet": lambda: robust_pcbf_slack_problem(SYS, X, U, h_f, N, DELTAS,
                                                               "E"),
    "X not a polytope": lambda: robust_pcbf_slack_problem(SYS, Ellipsoid(np.eye(2)), U, h_f,
                                                          N, DELTAS, ERROR),
    "slack_cost NaN": lambda: slack_cost(np.zeros((2, 2)), float("nan"), 1.0),
    "slack_cost alpha_f<0": lambda: slack_cost(np.zeros((2, 2)), 0.0, -1.0),
    "decrease_bound rho=1": lambda: decrease_bound(1.0, 1.0, 1.0),
    "multiobjective_lyapunov design string": lambda: multiobjective_lyapunov_problem("d"),
    "decrease_bound NaN": lambda: decrease_bound(float("nan"), 1.0, 0.5),
})
many("terminal CBF SDP", {
    "decrease factor 0": lambda: synthesize_terminal_cbf(A, B, X, U, decrease_factor=0.0),
    "decrease factor NaN": lambda: synthesize_terminal_cbf(A, B, X, U, decrease_factor=np.nan),
    "delta_N NaN": lambda: synthesize_terminal_cbf(A, B, X, U, delta_N=np.nan),
    "delta_N too large": lambda: synthesize_terminal_cbf(A, B, X, U, delta_N=2.0),
    "X not a polytope": lambda: synthesize_terminal_cbf(A, B, Ellipsoid(np.eye(2)), U),
    "A wrong shape": lambda: synthesize_terminal_cbf(np.ones((2, 3)), B, X, U),
})
many("approximate builders", {
    "eps<0": lambda: approximate_filter_problem(SYS, U, h_f, eps=-1.0),
    "h_hat string": lambda: max_decrease_problem(SYS, U, "h"),
    "h_hat math.sin": lambda: max_decrease_problem(SYS, U, lambda x: math.sin(x[0])),
    "h_hat vector": lambda: max_decrease_problem(SYS, U, lambda x: x),
    "U wrong dim": lambda: max_decrease_problem(SYS, X, h_f),
})

# -- compile, solve, Solution, verify -----------------------------------------------------------
many("compile", {
    "not an OCP": lambda: compile("not an ocp"),
    "None": lambda: compile(None),
    "unknown backend": lambda: compile(compiled()[0], "julia"),
    "backend not a string": lambda: compile(compiled()[0], 3),
    "no decision variables": lambda: compile(OCP(name="empty")),
    "zero-size variable only": lambda: compile(_zero_var()),
    "solver not a string": lambda: compile(compiled()[0], "casadi", 3),
    "options a list": lambda: compile(compiled()[0], "casadi", "ipopt", [1]),
    "retries a string": lambda: compile(compiled()[0], "casadi", "ipopt", None, "x"),
})


def _zero_var() -> OCP:
    o = OCP(name="zero")
    o.variable("v", 0)
    return o


def _parameter_free(backend: str) -> tuple[OCP, Solution]:
    o = OCP(name="free")
    v = o.variable("v", 1, lb=-1.0, ub=1.0)
    if backend == "cvxpy":
        o.minimize(v ** 2)
    return o, compile(o, backend).solve()


for _b in ("casadi", "cvxpy"):
    case(f"parameter-free problem verifies ({_b})", expect="any")(
        lambda b=_b: _parameter_free(b))
many("Compiled.solve", {
    "params list": lambda: compiled()[1].solve([0.1, 0.0]),
    "params string": lambda: compiled()[1].solve("x0"),
    "value string": lambda: compiled()[1].solve({"x0": "ab"}),
    "value None": lambda: compiled()[1].solve({"x0": None}),
    "value NaN": lambda: compiled()[1].solve({"x0": [np.nan, 0.0]}),
    "value wrong shape": lambda: compiled()[1].solve({"x0": [0.0, 0.0, 0.0]}),
    "unknown name": lambda: compiled()[1].solve({"x0": [0.0, 0.0], "y": 1.0}),
    "unknown names of mixed types": lambda: compiled()[1].solve({"x0": [0.0, 0.0], 1: 1.0,
                                                                 "y": 2.0}),
    "missing name": lambda: compiled()[1].solve({}),
    "casadi params list": lambda: compiled("casadi")[1].solve([0.1, 0.0]),
    "casadi value inf": lambda: compiled("casadi")[1].solve({"x0": [np.inf, 0.0]}),
}, match="x0")


def _edited(value: object) -> tuple[OCP, Solution]:
    ocp, sol = solved()
    sol.primal["u"] = np.full_like(sol.primal["u"], value)
    return ocp, sol


many("Solution", {
    "missing name": lambda: solved()[1]["xi_typo"],
    "w of the wrong size": lambda: Solution("optimal", 0.0, {"a": np.zeros(2)}, {}, 0.0,
                                            0, "none", "none", w=np.ones(3), p=np.zeros(0)),
    "w of strings": lambda: Solution("optimal", 0.0, {"a": np.zeros(2)}, {}, 0.0,
                                     0, "none", "none", w=["a", "b"], p=np.zeros(0)),
    "primal not a dict": lambda: Solution("optimal", 0.0, [1.0], {}, 0.0, 0, "none", "none"),
    "w setter wrong size": lambda: setattr(solved()[1], "w", np.zeros(1)),
}, match="")
many("verify", {
    "solution is a dict": lambda: verify(compiled()[0], {"x": 1}),
    "problem is a string": lambda: verify("ocp", solved()[1]),
    "other problem": lambda: verify(_slack(N=2, deltas=[0.0, 0.0]), solved()[1]),
    "tol negative": lambda: verify(*solved(), tol=-1.0),
    "tol NaN": lambda: verify(*solved(), tol=np.nan),
    "primal missing a variable": lambda: verify(compiled()[0], _drop(solved()[1], "u")),
    "primal wrong shape": lambda: verify(compiled()[0], _reshape(solved()[1], "xi")),
})
case("verify: edited primal NaN is a violation", expect="any")(
    lambda: _not_ok(verify(*_edited(np.nan))))
case("verify: edited primal outside U is a violation", expect="any")(
    lambda: _not_ok(verify(*_edited(5.0))))



@case("verify: a NaN block value is a violation", expect="any")
def _nan_block():
    ocp = OCP(name="sqrt")
    v = ocp.variable("v", 1)
    ocp.le(ca.sqrt(v), 1.0, name="root")
    ocp.minimize(v)
    point = Solution("optimal", -1.0, {"v": np.array([-1.0])}, {}, 0.0, 0, "hand", "hand")
    report = verify(ocp, point)
    assert np.isinf(report.block_violation["root"]), report
    return _not_ok(report)


def _drop(sol: Solution, name: str) -> Solution:
    sol.primal.pop(name)
    return sol


def _reshape(sol: Solution, name: str) -> Solution:
    sol.primal[name] = sol.primal[name].T
    return sol


def _not_ok(report: object) -> str:
    if report.ok:
        raise AssertionError(f"verify reported ok: {report}")
    return "violation seen"


# -- controllers and simulate -------------------------------------------------------------------
_FILTER: list[PCBFSafetyFilter] = []


def pcbf_filter() -> PCBFSafetyFilter:
    if not _FILTER:
        _FILTER.append(PCBFSafetyFilter.build(SYS, X, U, h_f, N, DELTAS, alpha_f=1e3,
                                              target="cvxpy"))
    return _FILTER[0]


class _Hold:
    """A controller that applies its proposal."""

    def step(self, x: np.ndarray, u_p: np.ndarray) -> tuple[np.ndarray, StepInfo]:
        return u_p, StepInfo()

    def reset(self) -> None:
        pass


many("controller step", {
    "x string": lambda: pcbf_filter().step("ab", [0.0]),
    "u_p string": lambda: pcbf_filter().step([0.0, 0.0], "ab"),
    "u_p wrong size": lambda: pcbf_filter().step([0.0, 0.0], [0.0, 0.0]),
    "x wrong size": lambda: pcbf_filter().step([0.0, 0.0, 0.0], [0.0]),
})
case("controller step: x NaN falls back honestly", expect="any")(
    lambda: pcbf_filter().step([np.nan, 0.0], [0.0])[1].fallback or "no fallback")
case("controller step: u_p NaN is read as 0 and filtered", expect="any")(
    lambda: pcbf_filter().step([0.0, 0.0], [np.nan])[1].status)
many("simulate", {
    "disturbance too short": lambda: simulate(LinearSystem(A, B, np.eye(2)), _Hold(),
                                              [0.0, 0.0], 5, 0.0, np.zeros((3, 2))),
    "disturbance NaN": lambda: simulate(LinearSystem(A, B, np.eye(2)), _Hold(), [0.0, 0.0],
                                        2, 0.0, np.full((2, 2), np.nan)),
    "disturbance wrong width": lambda: simulate(LinearSystem(A, B, np.eye(2)), _Hold(),
                                                [0.0, 0.0], 2, 0.0, np.zeros((2, 3))),
    "steps=-1": lambda: simulate(SYS, _Hold(), [0.0, 0.0], -1),
    "steps=2.5": lambda: simulate(SYS, _Hold(), [0.0, 0.0], 2.5),
    "x0 wrong size": lambda: simulate(SYS, _Hold(), [0.0], 2),
    "x0 NaN": lambda: simulate(SYS, _Hold(), [np.nan, 0.0], 2),
    "proposal string": lambda: simulate(SYS, _Hold(), [0.0, 0.0], 2, "u"),
    "controller without step": lambda: simulate(SYS, object(), [0.0, 0.0], 2),
    "controller returns u only": lambda: simulate(SYS, _NoInfo(), [0.0, 0.0], 2),
    "plant not a System": lambda: simulate(A, _Hold(), [0.0, 0.0], 2),
})
case("simulate: divergence stops the run", expect="any")(
    lambda: simulate(LinearSystem([[1e6]], [[1.0]]), _Hold(), [1.0], 5))


class _NoInfo(_Hold):
    def step(self, x: np.ndarray, u_p: np.ndarray) -> np.ndarray:  # type: ignore[override]
        return u_p


case("balustrade.compile/verify exported", expect="any")(
    lambda: (balustrade.compile is compile and balustrade.verify is verify) or
    (_ for _ in ()).throw(AssertionError("not exported")))

# -- solves on extreme data (subprocess: a crash must not kill the run) ------------------------
for _backend in ("cvxpy", "casadi"):
    for _label, _x0 in (("1e8", (1e8, 0.0)), ("-1e12", (-1e12, 1e12)), ("1e-300", (1e-300, 0)),
                        ("max float", (np.finfo(float).max / 1e10, 0.0))):
        case(f"extreme x0 {_label} ({_backend})", expect="any", risky=True)(
            lambda b=_backend, x=_x0: solved(b, x))
for _alpha in (1e300, 1e-300):
    case(f"extreme alpha_f {_alpha:g} (casadi)", expect="any", risky=True)(
        lambda a=_alpha: (lambda o: (o, compile(o, "casadi", "ipopt").solve({"x0": [2.0, 0.0]})))(
            _slack(alpha_f=a)))
case("tiny box (cvxpy)", expect="any", risky=True)(
    lambda: _solve_small_box(1e-12))


def _solve_small_box(width: float) -> tuple[OCP, Solution]:
    ocp = pcbf_slack_problem(SYS, Box.symmetric(width, dim=2), Box.symmetric(width, dim=1),
                             h_f, N, DELTAS)
    return ocp, compile(ocp, "cvxpy").solve({"x0": [0.5, 0.0]})


SAFE = [name for name, c in CASES.items() if not c.risky]
RISKY = [name for name, c in CASES.items() if c.risky]


@pytest.mark.parametrize("name", SAFE)
def test_named_case(name: str) -> None:
    c = CASES[name]
    outcome, detail = classify(c.run)
    check_case(c, outcome, detail)


def run_risky() -> None:
    """Subprocess entry: run the risky cases, one JSON line each, flushed before the next."""
    for name in RISKY:
        print(json.dumps({"start": name}), flush=True)
        outcome, detail = classify(CASES[name].run)
        print(json.dumps({"name": name, "outcome": outcome, "detail": detail[:500]}),
              flush=True)


def test_risky_cases_in_a_subprocess() -> None:
    proc = subprocess.run([sys.executable, str(Path(__file__)), "--risky"], capture_output=True,
                          text=True, timeout=300)
    lines = [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]
    done = {d["name"]: d for d in lines if "name" in d}
    started = [d["start"] for d in lines if "start" in d]
    crashed = [n for n in started if n not in done]
    assert proc.returncode == 0 and not crashed, \
        f"subprocess died (rc {proc.returncode}) in {crashed}: {proc.stderr[-2000:]}"
    for name in RISKY:
        check_case(CASES[name], done[name]["outcome"], done[name]["detail"])


# -- hypothesis: random arrays into the constructors and solve ---------------------------------
_floats = st.floats(allow_nan=True, allow_infinity=True, width=64)
_junk = st.one_of(
    st.lists(_floats, max_size=4),
    st.lists(st.lists(_floats, min_size=0, max_size=3), max_size=3),
    st.just("abc"), st.none(), st.just([[1.0, 2.0], [3.0]]),
    _floats, st.sampled_from([1e300, -1e300, 1e-300, 0.0]),
)


def _tally_property(fn: Callable[[], object], expect_ok: bool | None = None) -> str:
    outcome, detail = classify(fn)
    check_case(Case("property", fn, "any"), outcome, detail)
    if expect_ok is not None:
        assert (outcome == "ok") == expect_ok or outcome == "status", (outcome, detail)
    return outcome


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(a=_junk, b=_junk)
def test_constructors_property(a: object, b: object) -> None:
    """Junk into every set and system constructor: a clean error or a sound object."""
    for fn in (lambda: LinearSystem(a, b), lambda: Box(a, b), lambda: Polytope(a, b),
               lambda: Ellipsoid(a), lambda: Ellipsoid(np.eye(2), b)):
        if _tally_property(fn) == "ok":
            obj = fn()
            for arr in (getattr(obj, k, None) for k in ("A", "B", "H", "h", "P", "center")):
                if arr is not None:
                    assert np.all(np.isfinite(arr)), obj


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(alpha_f=st.one_of(_floats, st.just("1")), eps=_floats,
       deltas=st.one_of(st.lists(_floats, min_size=0, max_size=4), _floats))
def test_builder_arguments_property(alpha_f: object, eps: float, deltas: object) -> None:
    """A builder accepts its numbers iff they are valid (finite, signs, length N)."""
    d = np.asarray(deltas, dtype=float)
    full = np.full(N, float(d)) if d.ndim == 0 else d
    d_ok = bool((d.ndim == 0 or d.size == N) and np.all(np.isfinite(d)) and np.all(d >= 0)
                and full[0] == 0 and np.all(np.diff(full) >= 0))   # SPEC §1.4: 0 = Δ_0 <= …
    a_ok = isinstance(alpha_f, float) and np.isfinite(alpha_f) and alpha_f > 0
    _tally_property(lambda: _slack(alpha_f=alpha_f, deltas=deltas), expect_ok=d_ok and a_ok)
    e_ok = bool(np.isfinite(eps) and eps >= 0)
    _tally_property(lambda: pcbf_filter_problem(SYS, X, U, h_f, N, DELTAS, eps=eps),
                    expect_ok=e_ok)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(x0=st.one_of(st.lists(st.floats(-1e6, 1e6), min_size=2, max_size=2), _junk))
def test_solve_property(x0: object) -> None:
    """Any parameter value: a clean error, an honest status, or a solution that verifies."""
    ocp, c = compiled("cvxpy")
    _tally_property(lambda: (ocp, c.solve({"x0": x0})))


# -- every argument of every builder × a pool of junk values -----------------------------------
JUNK = [None, "ab", -1, 0, 2.5, np.nan, np.inf, -np.inf, 1e308, [], [1.0], [np.nan, 1.0],
        -np.eye(2), np.ones((3, 3)), [[1, 2], [3]], True, {}, (1, 2), ca.SX.sym("s", 2), X, U,
        h_f, SYS, ERROR, np.zeros(4), 1j, object()]
_W = Box([-0.01, -0.01], [0.01, 0.01], name="W")
_K = np.array([[-1.0, -1.5]])
ENTRIES: dict[str, tuple[Callable, list]] = {
    "pcbf_slack_problem": (pcbf_slack_problem, [SYS, X, U, h_f, N, DELTAS, 1e3, 1]),
    "pcbf_filter_problem": (pcbf_filter_problem, [SYS, X, U, h_f, N, DELTAS, 1e-6]),
    "extended_pcbf_problem": (extended_pcbf_problem, [SYS, X, U, h_f, N, DELTAS]),
    "mpc_problem": (mpc_problem, [SYS, X, U, None, N, np.eye(2), np.eye(1), np.eye(2)]),
    "soft_mpc_problem": (soft_mpc_problem, [SYS, X, U, X, N, np.eye(2), np.eye(1), np.eye(2),
                                            1e3, 1]),
    "predictive_safety_filter": (predictive_safety_filter, [SYS, X, U, X, N]),
    "cbf_filter_problem": (cbf_filter_problem, [SYS, U, h_f, 0.1]),
    "robust_pcbf_slack_problem": (robust_pcbf_slack_problem, [SYS, X, U, h_f, N, DELTAS, ERROR,
                                                              1e3, 1]),
    "robust_pcbf_filter_problem": (robust_pcbf_filter_problem, [SYS, X, U, h_f, N, DELTAS,
                                                                ERROR, 1e-6]),
    "tube_mpc_problem": (tube_mpc_problem, [SYS, X, U, X, N, ERROR, np.eye(2), np.eye(1),
                                            np.eye(2)]),
    "robust_mpc_problem": (robust_mpc_problem, [SYS, X, U, X, N, A + B @ _K, _K, _W, np.eye(2),
                                                np.eye(1), np.eye(2)]),
    "multiobjective_pcbf_problem": (multiobjective_pcbf_problem, [SYS, X, U, h_f, N, DELTAS,
                                                                  ERROR, 1e3]),
    "max_decrease_problem": (max_decrease_problem, [SYS, U, h_f]),
    "approximate_filter_problem": (approximate_filter_problem, [SYS, U, h_f, 1e-6]),
    "reachable_tightened_sets": (reachable_tightened_sets, [X, 0.5 * A, _W, N]),
    "tighten": (tighten, [X, Ellipsoid(np.eye(2) * 100)]),
    "tighten_by_feedback": (tighten_by_feedback, [U, _K, Ellipsoid(np.eye(2) * 100)]),
    "is_rpi": (is_rpi, [Ellipsoid(np.eye(2)), 0.5 * A, _W]),
    "slack_cost": (slack_cost, [np.zeros((2, 2)), 0.0, 1.0]),
    "combined_h": (combined_h, [0.0, 0.0, 1.0]),
    "decrease_bound (6.15g)": (decrease_bound, [1.0, 1.0, 0.5]),
    "Box": (Box, [[0.0], [1.0]]),
    "Polytope": (Polytope, [np.eye(2), np.ones(2)]),
    "Ellipsoid": (Ellipsoid, [np.eye(2), None]),
    "FunctionSet": (FunctionSet, [h_f, 2]),
    "LinearSystem": (LinearSystem, [A, B, None]),
    "System": (System, [lambda x, u: x + ca.mtimes(ca.DM(B), u), 2, 1]),
    "System.from_continuous": (System.from_continuous, [lambda x, u: -x, 2, 1, 0.1]),
    "norm": (norm, [ca.SX.sym("a", 2), 2]),
    "quad": (quad, [ca.SX.sym("a", 2), np.eye(2)]),
    "OCP": (OCP, [SYS, N]),
    "OCP.parameter": (lambda *a: OCP().parameter(*a), ["p", 2, 1, None]),
    "OCP.variable": (lambda *a: OCP().variable(*a), ["v", 2, 1, -1.0, 1.0, 0.0]),
    "OCP.state_constraint": (lambda *a: _ocp().state_constraint(*a), [X, None, None, None]),
    "OCP.input_constraint": (lambda *a: _ocp().input_constraint(*a), [U, None, None]),
    "OCP.terminal_constraint": (lambda *a: _ocp().terminal_constraint(*a), [X, 0.0, None]),
    "OCP.terminal_cbf": (lambda *a: _ocp().terminal_cbf(*a), [h_f, None]),
    "OCP.initial_tube": (lambda *a: OCP(SYS, N).initial_tube(*a), [[0.0, 0.0], X]),
    "OCP.dynamics": (lambda *a: OCP(SYS, N).dynamics(*a), [None, None]),
    "OCP.le": (lambda *a: _ocp().le(*a), [1.0, 2.0]),
    "OCP.minimize": (lambda *a: _ocp().minimize(*a), [1.0]),
    "Set.scale": (X.scale, [2.0]),
    "Set.translate": (X.translate, [[0.0, 0.0]]),
    "Set.linear_map": (X.linear_map, [np.eye(2)]),
    "Set.sample": (X.sample, [3, 0]),
    "Set.contains": (X.contains, [[0.0, 0.0], 1e-9]),
    "Set.support": (X.support, [[1.0, 0.0]]),
    "Set.is_subset_of": (X.is_subset_of, [X, 1e-7]),
    "Ellipsoid.scale": (Ellipsoid(np.eye(2)).scale, [2.0]),
    "System.step": (SYS.step, [[0.0, 0.0], [0.0]]),
    "Compiled.solve": (lambda *a: compiled()[1].solve(*a), [{"x0": [0.1, 0.0]}]),
    "verify": (verify, [compiled()[0], solved()[1], 1e-6]),
    "simulate": (simulate, [SYS, _Hold(), [0.0, 0.0], 2, 0.0, None]),
}


@pytest.mark.parametrize("entry", sorted(ENTRIES))
def test_junk_in_every_argument(entry: str) -> None:
    """Each argument of each entry point, replaced by each junk value: a BalustradeError
    or a sound result, never a raw exception."""
    fn, base = ENTRIES[entry]

    def call(args: list) -> object:  # a solve is judged with its problem (verify)
        return (compiled()[0], fn(*args)) if entry == "Compiled.solve" else fn(*args)

    assert classify(lambda: call(base))[0] == "ok", f"{entry}: the valid call fails"
    for i in range(len(base)):
        for junk in JUNK:
            args = list(base)
            args[i] = junk
            outcome, detail = classify(lambda a=args: call(a))
            check_case(Case(f"{entry}[{i}] = {junk!r:.30}", fn, "any"), outcome, detail)


def test_zz_tally() -> None:
    """Print the suite's counts (run with ``-s``); no raw exceptions, no bad results."""
    print(f"\nbad-input suite: {TALLY['cases']} cases, {TALLY['error']} clean errors, "
          f"{TALLY['status']} statuses, {TALLY['ok']} valid inputs accepted soundly, "
          f"{TALLY['raw']} raw exceptions, {TALLY['bad']} bad results")
    assert TALLY["raw"] == 0 and TALLY["bad"] == 0


if __name__ == "__main__":
    if "--risky" in sys.argv:
        run_risky()
    else:
        for name, c in CASES.items():
            outcome, detail = classify(c.run)
            TALLY["cases"] += 1
            TALLY[outcome] += 1
            if outcome in ("raw", "bad") or (c.expect == "error" and outcome != "error"):
                print(f"FAIL {name}: {outcome}: {detail}")
        print(f"{TALLY['cases']} named cases, {TALLY['error']} clean errors, "
              f"{TALLY['status']} statuses, {TALLY['ok']} accepted, {TALLY['raw']} raw "
              f"exceptions, {TALLY['bad']} bad results")
