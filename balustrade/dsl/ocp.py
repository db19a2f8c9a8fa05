"""The horizon problem builder.

An :class:`OCP` is data: decision variables, parameters (values given at solve time),
named constraint blocks (``g(w, p) == 0`` or ``g(w, p) <= 0``) and a cost made of
:mod:`balustrade.dsl.costs` terms. The methods below add the blocks the thesis'
formulations are made of, so that a formulation reads like its equations in SPEC.md::

    ocp = OCP(pendulum, N=10, name="pcbf_slack")            # (2.24)
    x0 = ocp.parameter("x0", 2)
    ocp.initial_state(x0)                                   # x_{0|k} = x_k
    ocp.dynamics()                                          # x_{i+1|k} = f(x_{i|k}, u_{i|k})
    ocp.input_constraint(U)                                 # u_{i|k} ∈ U
    xi = ocp.state_constraint(X, tightening=deltas, slack="variable")   # x_{i|k} ∈ X̄_i(ξ_i)
    xi_N = ocp.terminal_cbf(h_f, slack="variable")          # h_f(x_{N|k}) <= ξ_N
    ocp.minimize(alpha_f * xi_N + sum_norms(xi, 1))

Nothing here knows about backends (DESIGN.md); :mod:`balustrade.backends` lowers blocks.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import StrEnum

import casadi as ca
import numpy as np

from balustrade._checks import (
    as_count,
    as_float_array,
    as_scalar,
    as_vector,
    check_callable,
    check_name,
    check_symbolic,
)
from balustrade.dsl.costs import Cost
from balustrade.dsl.layout import Layout
from balustrade.dsl.sets import Set
from balustrade.dsl.system import System
from balustrade.errors import BalustradeError, NonFiniteError, ShapeError

SlackSpec = str | ca.SX | None
Tightening = float | Sequence[float] | np.ndarray | Callable[[int], float] | None


class VariableRole(StrEnum):
    """What a decision variable is (``role == "slack"`` keeps working: a ``str`` enum)."""

    FREE = "free"
    STATE = "state"
    INPUT = "input"
    SLACK = "slack"
    EPIGRAPH = "epigraph"


class BlockKind(StrEnum):
    """``expr == 0`` (``EQ``) or ``expr <= 0`` (``LE``)."""

    EQ = "eq"
    LE = "le"


class BlockTag(StrEnum):
    """What a constraint block is, e.g. for :func:`balustrade.verify`'s dynamics residual."""

    GENERIC = "generic"
    DYNAMICS = "dynamics"
    INITIAL = "initial"
    STATE = "state"
    INPUT = "input"
    TERMINAL = "terminal"
    TERMINAL_CBF = "terminal_cbf"
    DECREASE = "decrease"
    TUBE = "tube"
    RATE = "rate"


def _member(enum: type[StrEnum], value: object, where: str) -> StrEnum:
    """``enum(value)``, or an error naming ``where`` and the allowed values."""
    try:
        return enum(value)
    except ValueError:
        raise BalustradeError(f"{where}: unknown {enum.__name__} {value!r}; use one of "
                              f"{[m.value for m in enum]}") from None


@dataclass
class Variable:
    """A decision variable (a matrix of CasADi symbols) with simple bounds."""

    name: str
    sym: ca.SX
    lb: np.ndarray
    ub: np.ndarray
    init: np.ndarray
    role: VariableRole = VariableRole.FREE
    shape: tuple[int, int] = (0, 0)  # plain ints, read on every solve

    def __post_init__(self) -> None:
        self.shape = (int(self.sym.shape[0]), int(self.sym.shape[1]))
        self.role = _member(VariableRole, self.role, f"variable {self.name!r}: role")


@dataclass
class Parameter:
    """A parameter: a symbol whose value is given at solve time (``PAR`` in SPEC.md)."""

    name: str
    sym: ca.SX
    default: np.ndarray | None = None
    shape: tuple[int, int] = (0, 0)  # plain ints, read on every solve
    #: a lower bound every value must satisfy (checked when values are packed), or None
    lb: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.shape = (int(self.sym.shape[0]), int(self.sym.shape[1]))


@dataclass
class Block:
    """A named constraint block ``expr == 0`` (``kind='eq'``) or ``expr <= 0`` (``'le'``).

    ``tag`` says what the block is (``dynamics``, ``initial``, ``state``, ``input``,
    ``terminal``, ``terminal_cbf``, ``decrease``, ``tube``, ``generic``) so that
    :func:`balustrade.verify` can report dynamics residuals separately.
    """

    name: str
    kind: BlockKind
    expr: ca.SX
    tag: BlockTag = BlockTag.GENERIC
    info: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.kind = _member(BlockKind, self.kind, f"block {self.name!r}: kind")
        self.tag = _member(BlockTag, self.tag, f"block {self.name!r}: tag")

    @property
    def rows(self) -> int:
        return int(self.expr.numel())


class OCP:
    """A horizon optimal control problem over ``N`` steps of ``system`` (or none).

    With a system, state and input trajectories are created at once: ``ocp.x`` is
    ``(nx, N+1)`` and ``ocp.u`` is ``(nu, N)`` (names configurable, e.g. ``z``/``v`` for the
    nominal trajectories of tube formulations (2.15), (5.15)).
    """

    def __init__(self, system: System | None = None, N: int = 0, name: str = "ocp",
                 state_name: str = "x", input_name: str = "u"):
        check_name(name, "OCP: name")
        if system is not None and not isinstance(system, System):
            raise BalustradeError(f"{name}: expected a balustrade System (or None), got "
                                  f"{type(system).__name__}")
        if system is not None and (not isinstance(N, (int, np.integer)) or isinstance(N, bool)
                                   or N < 1):
            raise BalustradeError(f"{name}: horizon N must be a positive integer, got {N!r}")
        self.system, self.N, self.name = system, int(N), name
        self.variables: dict[str, Variable] = {}
        self.parameters: dict[str, Parameter] = {}
        self.blocks: list[Block] = []
        self._vlayout: Layout | None = None  # built on first use, see variable_layout
        self._playout: Layout | None = None
        self.cost = Cost()
        self.x: ca.SX | None = None
        self.u: ca.SX | None = None
        self.state_name, self.input_name = state_name, input_name
        if system is not None:
            self.x = self.variable(state_name, system.nx, self.N + 1, role="state")
            self.u = self.variable(input_name, system.nu, self.N, role="input")

    # -- symbols ---------------------------------------------------------------------
    def variable(self, name: str, rows: int, cols: int = 1, lb: object = -np.inf,
                 ub: object = np.inf, init: object = 0.0,
                 role: VariableRole | str = VariableRole.FREE) -> ca.SX:
        """Add a decision variable of shape ``(rows, cols)`` and return its symbol.

        ``lb``/``ub`` may be infinite but not NaN, with ``lb <= ub``; ``init`` is finite."""
        self._check_new_name(name)
        shape = self._shape(name, rows, cols)
        where = f"{self.name}: variable {name!r}"
        role = _member(VariableRole, role, f"{where}: role")
        lo = _broadcast(lb, shape, f"{where}: lb")
        hi = _broadcast(ub, shape, f"{where}: ub")
        start = _broadcast(init, shape, f"{where}: init")
        for label, arr in (("lb", lo), ("ub", hi)):
            if np.any(np.isnan(arr)):
                raise NonFiniteError(f"{where}: {label} contains NaN (use ±inf for no bound)")
        if np.any(lo > hi):
            bad = np.argwhere(lo > hi)[0].tolist()
            raise BalustradeError(f"{where}: lower bound exceeds upper bound at entry {bad} "
                                  f"({lo[tuple(bad)]:g} > {hi[tuple(bad)]:g})")
        if not np.all(np.isfinite(start)):
            raise NonFiniteError(f"{where}: init contains NaN or inf")
        sym = ca.SX.sym(name, *shape)
        self.variables[name] = Variable(name, sym, lo, hi, start, role)
        return sym

    def parameter(self, name: str, rows: int, cols: int = 1,
                  value: object | None = None, lb: float | None = None) -> ca.SX:
        """Add a parameter of shape ``(rows, cols)``; its value is given at solve time.
        ``lb``: a lower bound on every entry (e.g. ``0`` for slacks ``ξ >= 0``); a value
        below it is refused when the parameters are packed, before any solver runs."""
        self._check_new_name(name)
        shape = self._shape(name, rows, cols)
        where = f"{self.name}: parameter {name!r}"
        default = None if value is None else _broadcast(value, shape, f"{where}: value")
        if default is not None and not np.all(np.isfinite(default)):
            raise NonFiniteError(f"{where}: value contains NaN or inf")
        low = None
        if lb is not None:
            low = np.full(shape, as_scalar(lb, f"{where}: lb"))
            if default is not None and np.any(default < low):
                raise BalustradeError(f"{where}: value below its lower bound {float(lb):g}")
        sym = ca.SX.sym(name, *shape)
        self.parameters[name] = Parameter(name, sym, default, lb=low)
        return sym

    def _shared_parameter(self, name: str, shapes: Sequence[tuple[int, int]],
                          what: str) -> ca.SX:
        """The parameter ``name`` if declared with one of ``shapes``, else a new one of
        ``shapes[0]`` (blocks that share a parameter: the previous input of the rate
        blocks, the references of tracking costs); errors say ``what`` it is."""
        if name in self.parameters:
            par = self.parameters[name]
            if par.shape not in shapes:
                unique = list(dict.fromkeys(shapes))
                raise ShapeError(f"{self.name}: {what} {name!r}", unique[0] if len(unique) == 1
                                 else " or ".join(map(str, unique)), par.shape)
            return par.sym
        if name in self.variables:
            raise BalustradeError(f"{self.name}: {what} {name!r} is a decision variable; it "
                                  "must be a parameter")
        return self.parameter(name, *shapes[0])

    def _shape(self, name: str, rows: object, cols: object) -> tuple[int, int]:
        return (as_count(rows, f"{self.name}: {name!r}: rows"),
                as_count(cols, f"{self.name}: {name!r}: cols"))

    def _check_new_name(self, name: str) -> None:
        check_name(name, f"{self.name}: symbol name")
        if not name.isidentifier():
            raise BalustradeError(f"{self.name}: symbol name {name!r} is not an identifier")
        if name in self.variables or name in self.parameters:
            raise BalustradeError(f"{self.name}: a variable or parameter named {name!r} "
                                  "already exists")

    # -- generic constraints ---------------------------------------------------------
    def eq(self, lhs: object, rhs: object = 0.0, name: str = "eq",
           tag: BlockTag | str = BlockTag.GENERIC,
           **info: object) -> Block:
        """Add ``lhs == rhs`` (elementwise) as a named block."""
        return self._add(name, "eq", lhs, rhs, tag, info)

    def le(self, lhs: object, rhs: object = 0.0, name: str = "le",
           tag: BlockTag | str = BlockTag.GENERIC,
           **info: object) -> Block:
        """Add ``lhs <= rhs`` (elementwise) as a named block."""
        return self._add(name, "le", lhs, rhs, tag, info)

    def _add(self, name: str, kind: BlockKind | str, lhs: object, rhs: object,
             tag: BlockTag | str, info: dict) -> Block:
        check_name(name, f"{self.name}: block name")
        tag = _member(BlockTag, tag, f"{self.name}: block {name!r}: tag")
        lhs_sx = _as_sx(lhs, f"{self.name}: block {name!r}: left side")
        rhs_sx = _as_sx(rhs, f"{self.name}: block {name!r}: right side")
        if rhs_sx.numel() not in (1, lhs_sx.numel()) and lhs_sx.numel() != 1:
            raise ShapeError(f"{self.name}: block {name!r}", f"right side of shape {lhs_sx.shape}"
                             " or a scalar", rhs_sx.shape)
        expr = check_symbolic(ca.vec(lhs_sx - rhs_sx), f"{self.name}: block {name!r}")
        unique = self._unique_block_name(name)
        block = Block(unique, kind, expr, tag, dict(info))
        self.blocks.append(block)
        return block

    def _unique_block_name(self, name: str) -> str:
        taken = {b.name for b in self.blocks}
        if name not in taken:
            return name
        k = 2
        while f"{name}_{k}" in taken:
            k += 1
        return f"{name}_{k}"

    def decrease(self, expr: object, bound: object, name: str = "decrease") -> Block:
        """A decrease constraint ``expr <= bound`` on any expression of the decision
        variables against a (parameter) bound, e.g. (6.3h) or (6.15g)."""
        return self.le(expr, bound, name=name, tag="decrease")

    # -- blocks of the thesis' formulations ---------------------------------------------
    def _need_system(self, what: str) -> System:
        if self.system is None or self.x is None or self.u is None:
            raise BalustradeError(f"{self.name}: {what} needs an OCP built with a system")
        return self.system

    def initial_state(self, x0: object, name: str = "initial_state") -> Block:
        """``x_{0|k} = x_k`` ((2.9), (2.24b))."""
        sys = self._need_system("initial_state")
        x0 = self._as_column(x0, sys.nx, f"{name}: x0")
        return self.eq(self.x[:, 0], x0, name=name, tag="initial")

    def initial_tube(self, x0: object, E: Set, name: str = "initial_tube") -> Block:
        """``x_k ∈ z_{0|k} ⊕ E``, i.e. ``x_k − z_{0|k} ∈ E`` ((2.15), (5.15b))."""
        sys = self._need_system("initial_tube")
        x0 = self._as_column(x0, sys.nx, f"{name}: x0")
        self._check_set_dim(E, sys.nx, name)
        return self.le(E.c(x0 - self.x[:, 0]), 0, name=name, tag="tube", set=E.name)

    def dynamics(self, w: object | None = None, theta: object | None = None,
                 name: str = "dynamics") -> Block:
        """``x_{i+1|k} = f(x_{i|k}, u_{i|k}, w, θ)`` for ``i ∈ I[0, N−1]`` (nominal: ``w = 0``)."""
        sys = self._need_system("dynamics")
        w = ca.DM.zeros(sys.nw) if w is None else self._as_column(w, sys.nw, f"{name}: w")
        theta = (ca.DM.zeros(sys.ntheta) if theta is None
                 else self._as_column(theta, sys.ntheta, f"{name}: theta"))
        residual = [self.x[:, i + 1] - sys(self.x[:, i], self.u[:, i], w, theta)
                    for i in range(self.N)]
        return self.eq(ca.horzcat(*residual), 0, name=name, tag="dynamics")

    def input_constraint(self, U: Set | Sequence[Set], steps: Sequence[int] | None = None,
                         tightening: Tightening = None, name: str = "input") -> Block:
        """``u_{i|k} ∈ U`` (or ``U_i`` per step, e.g. ``U ⊖ K E_i`` (2.14)) for the steps."""
        sys = self._need_system("input_constraint")
        steps = self._steps(steps, name)
        sets = self._per_step_sets(U, steps, sys.nu, name, last=self.N - 1)  # u: N columns
        delta = self._deltas(tightening, steps, name)
        rows = [S.c(self.u[:, i]) + d for S, i, d in zip(sets, steps, delta)]
        return self.le(ca.horzcat(*rows), 0, name=name, tag="input")

    def state_constraint(self, X: Set | Sequence[Set], steps: Sequence[int] | None = None,
                         tightening: Tightening = None, slack: SlackSpec = None,
                         signed: bool = False, name: str = "state") -> ca.SX | None:
        """``c_x(x_{i|k}) + Δ_i 1 <= ξ_{i|k}`` for ``i`` in ``steps`` (default ``I[0, N−1]``).

        * ``slack=None``: hard constraint ``x_{i|k} ∈ X̄_i(0)`` (SPEC §1.4);
        * ``slack="variable"``: one slack per constraint row and step, returned as an
          ``(n_rows, len(steps))`` symbol, ``ξ >= 0`` unless ``signed=True`` ((2.24), (7.8));
        * ``slack=<expression>``: slacks fixed to a parameter expression ((2.23), (5.16)).

        ``X`` may be a list of sets, one per step (reachable-set tightening (2.14)), and
        ``tightening`` a scalar, a sequence ``Δ_i`` over ``steps`` or a callable ``i ↦ Δ_i``.
        """
        sys = self._need_system("state_constraint")
        steps = self._steps(steps, name)
        sets = self._per_step_sets(X, steps, sys.nx, name)
        delta = self._deltas(tightening, steps, name)
        rows = [S.c(self.x[:, i]) + d for S, i, d in zip(sets, steps, delta)]
        n_rows = {int(r.numel()) for r in rows}
        if len(n_rows) != 1:
            raise ShapeError(f"{self.name}: {name}", "sets with the same number of rows per step",
                             sorted(n_rows), what="row counts")
        lhs = ca.horzcat(*rows)
        xi = self._slack(slack, lhs.shape, signed, name)
        if xi is None:
            self.le(lhs, 0, name=name, tag="state")
        else:
            self.le(lhs, xi, name=name, tag="state")
        return xi

    def terminal_constraint(self, Xf: Set, tightening: float = 0.0, slack: SlackSpec = None,
                            signed: bool = False, name: str = "terminal") -> ca.SX | None:
        """``c_{x,f}(x_{N|k}) + Δ <= ξ_N`` (hard when ``slack=None``) ((2.9), (2.11))."""
        sys = self._need_system("terminal_constraint")
        self._check_set_dim(Xf, sys.nx, name)
        delta = as_scalar(tightening, f"{self.name}: {name}: tightening", low=0.0)
        lhs = Xf.c(self.x[:, self.N]) + delta
        xi = self._slack(slack, lhs.shape, signed, name)
        self.le(lhs, 0 if xi is None else xi, name=name, tag="terminal")
        return xi

    def terminal_cbf(self, h_f: Callable[[ca.SX], object], slack: SlackSpec = None,
                     signed: bool = False, name: str = "terminal_cbf") -> ca.SX | None:
        """``h_f(x_{N|k}) <= ξ_{N|k}`` ((2.24), (5.15f)); hard ``h_f(x_N) <= 0`` if no slack."""
        sys = self._need_system("terminal_cbf")
        check_callable(h_f, f"{self.name}: {name}: h_f")
        try:
            value = ca.SX(h_f(self.x[:, self.N]))
        except Exception as exc:  # the user's function failed on a symbol
            raise BalustradeError(f"{self.name}: {name}: h_f(x) failed on a symbol of shape "
                                  f"({sys.nx}, 1): {exc}") from exc
        if value.numel() != 1:
            raise ShapeError(f"{self.name}: {name}: h_f(x)", "a scalar", value.shape)
        xi = self._slack(slack, (1, 1), signed, name)
        self.le(value, 0 if xi is None else xi, name=name, tag="terminal_cbf")
        return xi

    def joint_constraint(self, Z: object, x: ca.SX | None = None, u: ca.SX | None = None,
                         **kw: object) -> Block:
        """``F x_i + G u_i <= 1`` for a :class:`~balustrade.dsl.joint.JointPolytope` ``Z``
        (SPEC §2.20), also over tubes (see :func:`balustrade.dsl.joint.joint_constraint`)."""
        from balustrade.dsl.joint import joint_constraint

        return joint_constraint(self, Z, x, u, **kw)

    # -- engineering blocks (delegates: balustrade.dsl.rates, balustrade.dsl.tracking) ----
    def rate_limit(self, rate: object, soft: bool = False, u_prev: str | ca.SX = "u_prev",
                   name: str = "rate") -> ca.SX | None:
        """``|u_i − u_{i−1}| <= rate`` with ``u_{−1} = u_prev`` (see :mod:`~.rates`)."""
        from balustrade.dsl.rates import rate_limit

        return rate_limit(self, rate, soft=soft, u_prev=u_prev, name=name)

    def rate_cost(self, R: object | None = None, u_prev: str | ca.SX = "u_prev") -> Cost:
        """``Σ_i ‖u_i − u_{i−1}‖²_R`` with ``u_{−1} = u_prev`` (see :mod:`~.rates`)."""
        from balustrade.dsl.rates import rate_cost

        return rate_cost(self, R, u_prev=u_prev)

    def tracking_cost(self, Q: object | None = None, R: object | None = None,
                      P: object | None = None, **refs: object) -> Cost:
        """``Σ_i ‖x_i − r_i‖²_Q + ‖u_i − u^ref_i‖²_R + ‖x_N − r_N‖²_P`` (see
        :func:`balustrade.dsl.tracking.tracking_cost` for ``x_ref``, ``u_ref``, ...)."""
        from balustrade.dsl.tracking import tracking_cost

        return tracking_cost(self, Q, R, P, **refs)

    # -- cost ----------------------------------------------------------------------
    def minimize(self, cost: object) -> None:
        """Set the objective (a CasADi scalar, a :class:`Cost`, or a sum of both)."""
        cost = Cost.of(cost)
        for k, term in enumerate(cost.terms):
            label = f", {term.label}" if term.label else ""
            where = f"{self.name}: cost term {k} ({term.kind}{label})"
            if not np.isfinite(term.coef):
                raise NonFiniteError(f"{where}: coefficient is {term.coef}")
            check_symbolic(term.expr, where)
        self.cost = cost

    # -- helpers ---------------------------------------------------------------------
    def _slack(self, slack: SlackSpec, shape: tuple[int, int], signed: bool,
               block: str) -> ca.SX | None:
        if slack is None:
            return None
        if isinstance(slack, str):
            if slack != "variable":
                raise BalustradeError(f"{self.name}: {block}: slack must be None, 'variable' "
                                      f"or an expression, got {slack!r}")
            lb = -np.inf if signed else 0.0
            return self.variable(self._unique_symbol(f"xi_{block}"), shape[0], shape[1],
                                 lb=lb, role="slack")
        expr = _as_sx(slack, f"{self.name}: {block}: slack")
        if expr.shape != tuple(shape) and expr.numel() != 1:
            raise ShapeError(f"{self.name}: {block}: slack", tuple(shape), expr.shape)
        return expr

    def _unique_symbol(self, base: str) -> str:
        name, k = base, 2
        while name in self.variables or name in self.parameters:
            name, k = f"{base}_{k}", k + 1
        return name

    def _steps(self, steps: Sequence[int] | None, block: str) -> list[int]:
        if steps is None:
            return list(range(self.N))
        if isinstance(steps, (str, bytes, ca.SX, ca.MX, ca.DM)) \
                or not hasattr(steps, "__iter__"):
            raise BalustradeError(f"{self.name}: {block}: steps must be a sequence of step "
                                  f"indices, got {type(steps).__name__}")
        out = [as_count(i, f"{self.name}: {block}: step index") for i in steps]
        if not out:
            raise BalustradeError(f"{self.name}: {block}: steps is empty")
        return out

    def _per_step_sets(self, S: Set | Sequence[Set], steps: list[int], dim: int,
                       block: str, last: int | None = None) -> list[Set]:
        """One set per step of ``steps``, each of dimension ``dim``; steps in ``0..last``
        (default ``N``: the state columns; ``N − 1`` for the inputs)."""
        sets = list(S) if isinstance(S, (list, tuple)) else [S] * len(steps)
        if len(sets) != len(steps):
            raise ShapeError(f"{self.name}: {block}", f"{len(steps)} sets (one per step)",
                             f"{len(sets)} sets", what="")
        for s in sets:
            self._check_set_dim(s, dim, block)
        last = self.N if last is None else last
        bad = [i for i in steps if not 0 <= i <= last]
        if bad:
            raise BalustradeError(f"{self.name}: {block}: steps {bad} outside 0..{last}")
        return sets

    def _check_set_dim(self, S: Set, dim: int, block: str) -> None:
        if not isinstance(S, Set):
            raise BalustradeError(f"{self.name}: {block}: expected a balustrade Set, got "
                                  f"{type(S).__name__}")
        if S.dim != dim:
            raise ShapeError(f"{self.name}: {block}: set {S.name}", f"dimension {dim}",
                             f"dimension {S.dim}")

    def _deltas(self, tightening: Tightening, steps: list[int], block: str) -> list[float]:
        where = f"{self.name}: {block}: tightening"
        if tightening is None:
            return [0.0] * len(steps)
        if callable(tightening):
            values = []
            for i in steps:
                try:
                    value = tightening(i)
                except Exception as exc:  # the user's function failed
                    raise BalustradeError(f"{where}: Δ(i) failed at step {i}: {exc}") from exc
                values.append(as_scalar(value, f"{where} Δ_{i}", low=0.0))
            return values
        arr = as_float_array(tightening, where)
        if arr.ndim == 0:
            return [as_scalar(arr, where, low=0.0)] * len(steps)
        values = [float(d) for d in as_vector(arr, where, len(steps))]
        negative = [k for k, d in enumerate(values) if d < 0]
        if negative:
            # a negative Δ_i would relax the hard row c(x) + Δ_i <= 0 beyond the declared set
            # (SPEC §1.4: 0 = Δ_0 < Δ_1 < …; docs/language.md "Bad input")
            raise BalustradeError(f"{where}: Δ_i must be nonnegative (a negative one relaxes "
                                  f"the constraint beyond the declared set); entries "
                                  f"{negative} are {[values[k] for k in negative]}")
        return values

    def _as_column(self, value: object, size: int, block: str) -> ca.SX:
        if isinstance(value, (ca.SX, ca.DM)):
            value = ca.SX(value)
            if value.numel() != size:
                raise ShapeError(f"{self.name}: {block}", (size, 1), value.shape)
            return ca.vec(value)
        return ca.SX(ca.DM(as_vector(value, f"{self.name}: {block}", size)))

    # -- flattening (used by backends and verify) --------------------------------------
    def decision_vector(self) -> ca.SX:
        """All variables stacked (an empty ``SX`` column if there are none)."""
        return ca.vertcat(ca.SX(0, 1), *[ca.vec(v.sym) for v in self.variables.values()])

    def parameter_vector(self) -> ca.SX:
        """All parameters stacked (an empty ``SX`` column if there are none)."""
        return ca.vertcat(ca.SX(0, 1), *[ca.vec(p.sym) for p in self.parameters.values()])

    def constraint_vector(self) -> ca.SX:
        return ca.vertcat(ca.SX(0, 1), *[b.expr for b in self.blocks])

    @property
    def variable_layout(self) -> Layout:
        """The stacked decision vector: one :class:`~balustrade.dsl.layout.Layout` block per
        variable (declaration order, column-major), with bounds and initial values."""
        if self._vlayout is None or len(self._vlayout) != len(self.variables):
            self._vlayout = Layout.stack(
                ((v.name, v.shape, v.init, v.lb, v.ub) for v in self.variables.values()),
                owner=self.name, noun="variable", value_label="initial guess")
        return self._vlayout

    @property
    def parameter_layout(self) -> Layout:
        """The stacked parameter vector (declaration order, column-major; a parameter's
        declared value is its ``init``)."""
        if self._playout is None or len(self._playout) != len(self.parameters):
            self._playout = Layout.stack(
                ((p.name, p.shape, p.default, p.lb, None) for p in self.parameters.values()),
                owner=self.name, noun="parameter")
        return self._playout

    def pack_parameters(self, values: dict[str, object] | None) -> np.ndarray:
        """Stack parameter values (checked for shape and finiteness) in declaration order."""
        return self.parameter_layout.pack(values)

    def unpack_variables(self, w: np.ndarray) -> dict[str, np.ndarray]:
        """Split a stacked decision vector into named arrays of their declared shapes."""
        return self.variable_layout.unpack(w)

    def pack_variables(self, values: dict[str, object]) -> np.ndarray:
        """Stack named variable values (missing ones take their ``init``)."""
        if values is None:
            raise BalustradeError(f"{self.name}: variable values must be a dict name -> "
                                  "value, got NoneType")
        return self.variable_layout.pack(values)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.variable_layout.bounds()

    def describe(self) -> str:
        """A human-readable summary of symbols and blocks."""
        lines = [f"OCP {self.name!r}" + (f" over N={self.N} steps of {self.system.name}"
                                         if self.system else "")]
        for v in self.variables.values():
            lines.append(f"  var   {v.name:<16} {v.shape} ({v.role})")
        for p in self.parameters.values():
            lines.append(f"  par   {p.name:<16} {p.shape}")
        for b in self.blocks:
            op = "==" if b.kind == "eq" else "<="
            lines.append(f"  block {b.name:<16} {b.rows} rows {op} 0 ({b.tag})")
        lines.append(f"  cost  {len(self.cost.terms)} terms: "
                     + ", ".join(t.kind for t in self.cost.terms))
        return "\n".join(lines)


def _as_sx(value: object, block: str) -> ca.SX:
    if isinstance(value, ca.SX):
        return value
    if isinstance(value, ca.MX):
        raise BalustradeError(f"{block}: MX expressions are not supported; build blocks from "
                              "the OCP's SX symbols")
    if isinstance(value, ca.DM):
        return ca.SX(value)
    try:
        return ca.SX(ca.DM(as_float_array(value, block)))
    except BalustradeError:
        try:  # e.g. a list of SX entries
            return ca.SX(value)
        except Exception:  # noqa: BLE001 - not an expression: report the numeric error
            pass
        raise


def _broadcast(value: object, shape: tuple[int, int], block: str) -> np.ndarray:
    arr = as_float_array(value, block)
    if arr.ndim == 0:
        return np.full(shape, float(arr))
    if arr.size == shape[0] and shape[1] > 1 and arr.ndim == 1:
        return np.repeat(arr.reshape(-1, 1), shape[1], axis=1)
    if arr.size == shape[0] * shape[1]:
        return arr.reshape(shape) if arr.ndim == 2 else arr.reshape(shape, order="F")
    raise ShapeError(block, shape, arr.shape)
