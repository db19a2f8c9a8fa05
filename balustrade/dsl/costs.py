"""Cost terms of a horizon problem.

A cost is a nonnegative combination of terms. Smooth terms are plain CasADi scalars
(quadratics, linear terms, anything differentiable); the non-smooth convex terms that the
thesis uses are tagged so that every backend can lower them exactly:

* :func:`norm` — ``‖a‖₁``, ``‖a‖₂``, ``‖a‖∞`` of an expression (slack costs (2.24), (5.15);
  filter costs ``‖u₀ − u_p‖`` (2.19), (2.23));
* :func:`sum_norms` — ``Σ_i ‖ξ_i‖`` over the columns of a slack trajectory (SPEC §1.12);
* :func:`max_of` — ``max_j a_j`` (the extended PCBF value (7.8));
* :func:`quad` — ``aᵀ Q a`` with ``Q ⪰ 0`` checked (a smooth term).

CasADi lowers tagged terms to epigraph variables; cvxpy to ``cp.norm`` / ``cp.max``.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import casadi as ca
import numpy as np

from balustrade._checks import as_float_array, check_psd, check_symbolic, check_weight
from balustrade.errors import BalustradeError, NonFiniteError, ShapeError


class TermKind(StrEnum):
    """What a cost term is (a ``str`` enum: ``kind == "norm2"`` keeps working)."""

    SMOOTH = "smooth"
    SQUARED2 = "squared2"  # ‖expr‖₂²: smooth, but kept as a sum of squares
    NORM1 = "norm1"
    NORM2 = "norm2"
    NORMINF = "norminf"
    MAX = "max"

    @property
    def nonsmooth(self) -> bool:
        """A norm or max term (lowered to an epigraph or a cone)."""
        return self not in (TermKind.SMOOTH, TermKind.SQUARED2)


NORM_KINDS = {1: TermKind.NORM1, 2: TermKind.NORM2, np.inf: TermKind.NORMINF,
              "inf": TermKind.NORMINF}


@dataclass(frozen=True)
class Term:
    """One cost term ``coef · kind(expr)`` (:class:`TermKind`)."""

    kind: TermKind
    expr: ca.SX
    coef: float = 1.0
    label: str = ""

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "kind", TermKind(self.kind))
        except ValueError:
            raise BalustradeError(f"cost term {self.label!r}: unknown kind {self.kind!r}; use "
                                  f"one of {[k.value for k in TermKind]}") from None

    def scaled(self, factor: float) -> Term:
        return Term(self.kind, self.expr, self.coef * factor, self.label)

    def value_expr(self) -> ca.SX:
        """The term as a (non-smooth) CasADi expression, for evaluation only."""
        e = self.expr
        value = {
            "smooth": lambda: e,
            "squared2": lambda: ca.sumsqr(e),
            "norm1": lambda: ca.sum1(ca.fabs(e)),
            "norm2": lambda: ca.norm_2(e),
            "norminf": lambda: ca.mmax(ca.fabs(e)),
            "max": lambda: ca.mmax(e),
        }[self.kind]()
        return self.coef * value


class Cost:
    """A sum of :class:`Term` objects; supports ``+`` with CasADi scalars and numbers and
    multiplication by nonnegative numbers."""

    def __init__(self, terms: list[Term] | None = None):
        self.terms: list[Term] = list(terms or [])

    @staticmethod
    def of(value: object) -> Cost:
        """Coerce a CasADi scalar, a number, a :class:`Term` or a :class:`Cost`."""
        if isinstance(value, Cost):
            return value
        if isinstance(value, Term):
            return Cost([value])
        if isinstance(value, (int, float, np.floating, np.integer)) and not isinstance(value,
                                                                                       bool):
            if not np.isfinite(value):
                raise NonFiniteError(f"cost: a constant cost term is {value}")
            return Cost([Term(TermKind.SMOOTH, ca.SX(float(value)))])
        if isinstance(value, (ca.SX, ca.DM)):
            expr = ca.SX(value)
            if expr.numel() != 1:
                raise ShapeError("cost", "a scalar expression", expr.shape)
            return Cost([Term(TermKind.SMOOTH, check_symbolic(expr, "cost: smooth term"))])
        raise BalustradeError(f"cost: cannot use an object of type {type(value).__name__} as "
                              "a cost term (use a CasADi scalar, norm(), max_of(), quad())")

    def __add__(self, other: object) -> Cost:
        return Cost(self.terms + Cost.of(other).terms)

    __radd__ = __add__

    def __sub__(self, other: object) -> Cost:
        return self + (-1.0) * Cost.of(other)

    def __rsub__(self, other: object) -> Cost:
        return Cost.of(other) + (-1.0) * self

    def __neg__(self) -> Cost:
        return (-1.0) * self

    def __mul__(self, factor: object) -> Cost:
        if isinstance(factor, (ca.SX, ca.DM)) and ca.SX(factor).is_constant() \
                and ca.SX(factor).numel() == 1:
            factor = float(ca.DM(factor))
        if not isinstance(factor, (int, float, np.floating, np.integer)) \
                or isinstance(factor, bool):
            raise BalustradeError("cost: a cost can only be scaled by a number (got "
                                  f"{type(factor).__name__}; a parameter-dependent weight "
                                  "is not supported on norm or max terms)")
        factor = float(factor)
        if not np.isfinite(factor):
            raise NonFiniteError(f"cost: scale factor is {factor}")
        if factor < 0 and any(t.kind != TermKind.SMOOTH for t in self.terms):
            raise BalustradeError("cost: a norm or max term scaled by a negative number is not "
                                  "convex and cannot be lowered to an epigraph")
        return Cost([t.scaled(factor) for t in self.terms])

    __rmul__ = __mul__

    def expr(self) -> ca.SX:
        """The total cost as one CasADi expression (for evaluation and verification)."""
        total = ca.SX(0)
        for t in self.terms:
            total = total + t.value_expr()
        return total


def _as_sx(a: object, block: str) -> ca.SX:
    if isinstance(a, (ca.SX, ca.DM)):
        return check_symbolic(ca.vec(ca.SX(a)), block)
    if isinstance(a, (int, float, np.ndarray, list, tuple)) and not isinstance(a, bool):
        try:
            arr = as_float_array(a, block)
        except BalustradeError:
            try:  # a list of SX entries
                return check_symbolic(ca.vec(ca.vertcat(*a)), block)
            except Exception:  # noqa: BLE001 - report the numeric error
                pass
            raise
        if not np.all(np.isfinite(arr)):
            raise NonFiniteError(f"{block}: contains NaN or inf")
        return ca.vec(ca.SX(ca.DM(arr)))
    raise BalustradeError(f"{block}: expected a CasADi SX expression, got {type(a).__name__}")


def norm(a: object, ord: int | float | str = 2, label: str = "") -> Cost:
    """``‖a‖_ord`` for ``ord ∈ {1, 2, inf}`` (exactly lowered on every backend)."""
    if isinstance(ord, bool) or not isinstance(ord, (int, float, str)) or ord not in NORM_KINDS:
        raise BalustradeError(f"norm: unsupported order {ord!r}; use 1, 2 or inf")
    return Cost([Term(NORM_KINDS[ord], _as_sx(a, "norm"), 1.0, label)])


def squared_norm(a: object, label: str = "") -> Cost:
    """``‖a‖₂²`` (the squared Euclidean filter cost, SPEC §2.5 [Default])."""
    return Cost([Term(TermKind.SQUARED2, _as_sx(a, "squared_norm"), 1.0, label)])


def sum_norms(M: object, ord: int | float | str = 2, label: str = "") -> Cost:
    """``Σ_i ‖M[:, i]‖_ord``: the slack cost ``Σ_i ‖ξ_i‖`` of SPEC §1.12."""
    if not isinstance(M, ca.SX):
        raise BalustradeError(f"sum_norms: expected a CasADi SX matrix, got "
                              f"{type(M).__name__}")
    cost = Cost()
    for i in range(M.shape[1]):
        cost = cost + norm(M[:, i], ord, label=f"{label}[{i}]" if label else "")
    return cost


def max_of(a: object, label: str = "") -> Cost:
    """``max_j a_j`` (convex; lowered to an epigraph ``a_j <= t``)."""
    return Cost([Term(TermKind.MAX, _as_sx(a, "max_of"), 1.0, label)])


def quad(a: object, Q: object | None = None, label: str = "") -> ca.SX:
    """``aᵀ Q a`` with ``Q ⪰ 0`` checked (``Q = I`` by default); a smooth CasADi scalar."""
    a = _as_sx(a, "quad")
    if Q is None:
        return ca.sumsqr(a)
    Qm = check_psd(Q, f"quad{(' ' + label) if label else ''}: Q")
    if Qm.shape[0] != a.numel():
        raise ShapeError(f"quad{(' ' + label) if label else ''}: Q", (a.numel(), a.numel()),
                         Qm.shape)
    return ca.mtimes([a.T, ca.DM(Qm), a])


def weight_matrix(W: object | None, n: int, where: str) -> np.ndarray:
    """A PSD weight: ``None`` is ``I``, a scalar ``w I``, a vector ``diag(w)``."""
    if W is None:
        return np.eye(n)
    arr = as_float_array(W, where)
    if arr.ndim == 0:
        arr = float(arr) * np.eye(n)
    elif arr.ndim == 1:
        if arr.size != n:
            raise ShapeError(where, f"({n},) or ({n}, {n})", arr.shape)
        arr = np.diag(arr)
    return check_weight(arr, n, where)
