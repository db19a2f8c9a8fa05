"""The synthesis part of the language: semidefinite programs written like the thesis.

Offline designs — the terminal CBF (6.17)/(7.11), the ellipsoidal RPI set (5.14), the regret
syntheses (3.19)…(3.41) — are convex programs over *matrices*: symmetric / PSD matrix
variables, linear matrix inequalities (LMIs) built from blocks, second-order cones, linear and
log-det objectives. A :class:`SynthesisProblem` states one of them declaratively::

    sdp = SynthesisProblem("terminal ellipsoid")
    E = sdp.matrix("E", (n, n), symmetric=True)
    Y = sdp.matrix("Y", (m, n))
    sdp.lmi("invariance", bmat([[lam * E, (A @ E + B @ Y).T], [A @ E + B @ Y, E]]))
    sdp.maximize(logdet(E))

Expressions are a small tree (:class:`Expr`) with numpy shape semantics and a curvature
(affine / convex / concave) checked as they are built: a product of two variable expressions,
a convex function on the wrong side of ``<=``, or a concave objective to minimize is refused
with an error naming it, before any solver runs. Parameters (:meth:`SynthesisProblem.parameter`)
are data updated between solves without rebuilding the problem (DPP). The language imports no
solver: :func:`balustrade.backends.compile_synthesis` lowers the tree once (to cvxpy) and
solves it many times.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from balustrade._checks import check_name
from balustrade.errors import BalustradeError, ConvexityError, ShapeError

Shape = tuple[int, ...]
#: curvatures an expression can have; ``"unknown"`` is refused wherever it matters
CURVATURES = ("constant", "affine", "convex", "concave")


# -- declarations ---------------------------------------------------------------------------
@dataclass(frozen=True)
class VariableDecl:
    """A decision variable: ``shape``, and whether it is symmetric, PSD or nonnegative."""

    name: str
    shape: Shape
    symmetric: bool = False
    psd: bool = False
    nonneg: bool = False


@dataclass
class ParameterDecl:
    """Problem data updated between solves (``value`` is the default used when a solve
    gives none)."""

    name: str
    shape: Shape
    value: np.ndarray | None = None
    nonneg: bool = False
    symmetric: bool = False
    psd: bool = False


# -- expressions ----------------------------------------------------------------------------
def _ghost(shape: Shape) -> np.ndarray:
    """A read-only array of ``shape`` that allocates one number (for numpy's shape rules)."""
    return np.broadcast_to(np.zeros(()), shape)


def _matmul_shape(a: Shape, b: Shape) -> Shape:
    """numpy's ``@`` shape rule for 1-D and 2-D operands (raises ValueError on a mismatch)."""
    if a[-1] != b[0]:
        raise ValueError("inner dimensions")
    return a[:-1] + b[1:]


def _join(a: str, b: str) -> str:
    """Curvature of a sum."""
    if a == "constant":
        return b
    if b == "constant":
        return a
    if a == b:
        return a
    if "affine" in (a, b):
        return b if a == "affine" else a
    return "unknown"


_FLIP = {"constant": "constant", "affine": "affine", "convex": "concave", "concave": "convex",
         "unknown": "unknown"}


class Expr:
    """A node of a synthesis expression: ``op``, its ``args`` and static ``shape``.

    Supports ``+ - * / @``, ``.T``, indexing/slicing, and the comparisons ``==``, ``<=``,
    ``>=`` (elementwise) and ``>>``/``<<`` (semidefinite order), which return
    :class:`Constraint` objects to hand to :meth:`SynthesisProblem.subject_to`.
    """

    __array_ufunc__ = None  # numpy arrays defer to our reflected operators (A @ E)
    __hash__ = object.__hash__

    def __init__(self, op: str, args: tuple = (), shape: Shape = (),
                 curvature: str = "affine", has_var: bool = False, data: Any = None,
                 label: str = ""):
        self.op, self.args, self.shape = op, args, tuple(int(s) for s in shape)
        self.curvature, self.has_var, self.data = curvature, has_var, data
        self.label = label

    # -- naming -------------------------------------------------------------------------
    def __repr__(self) -> str:
        return f"Expr({self.describe()}, shape={self.shape}, {self.curvature})"

    def describe(self, depth: int = 3) -> str:
        """A short text of the expression for error messages (``depth`` levels, at most
        three arguments each)."""
        if self.op in ("variable", "parameter"):
            return self.data.name
        if self.op == "constant":
            return f"constant{self.shape}"
        if self.label:
            return self.label
        if depth <= 0:
            return f"{self.op}(…)"
        args = [a for a in self.args if isinstance(a, Expr)]
        inner = ", ".join(a.describe(depth - 1) for a in args[:3])
        return f"{self.op}({inner}{', …' if len(args) > 3 else ''})"

    @property
    def size(self) -> int:
        return int(np.prod(self.shape)) if self.shape else 1

    @property
    def ndim(self) -> int:
        return len(self.shape)

    @property
    def is_scalar(self) -> bool:
        return self.size == 1 and self.ndim <= 1

    # -- algebra --------------------------------------------------------------------------
    def __add__(self, other: object) -> Expr:
        other = as_expr(other)
        try:
            shape = np.broadcast_shapes(self.shape, other.shape)
        except ValueError:
            raise ShapeError(f"synthesis: {self.describe()} + {other.describe()}",
                             self.shape, other.shape, what="operand shapes") from None
        return Expr("add", (self, other), shape, _join(self.curvature, other.curvature),
                    self.has_var or other.has_var)

    def __radd__(self, other: object) -> Expr:
        return as_expr(other) + self

    def __neg__(self) -> Expr:
        return Expr("neg", (self,), self.shape, _FLIP[self.curvature], self.has_var)

    def __sub__(self, other: object) -> Expr:
        return self + (-as_expr(other))

    def __rsub__(self, other: object) -> Expr:
        return as_expr(other) + (-self)

    def __mul__(self, other: object) -> Expr:
        return _scale(self, as_expr(other))

    def __rmul__(self, other: object) -> Expr:
        return _scale(as_expr(other), self)

    def __truediv__(self, other: object) -> Expr:
        other = as_expr(other)
        if other.op != "constant" or not other.is_scalar:
            raise BalustradeError(f"synthesis: {self.describe()} / {other.describe()}: only "
                                  "division by a constant number is allowed")
        value = float(np.asarray(other.data).reshape(-1)[0])
        if value == 0:
            raise BalustradeError(f"synthesis: {self.describe()} / 0")
        scaled = _scale(self, as_expr(1.0 / value))  # shape and curvature of the quotient
        return Expr("div", (self, other), scaled.shape, scaled.curvature, self.has_var)

    def __matmul__(self, other: object) -> Expr:
        return _matmul(self, as_expr(other))

    def __rmatmul__(self, other: object) -> Expr:
        return _matmul(as_expr(other), self)

    @property
    def T(self) -> Expr:
        """Transpose (a 1-D expression is its own transpose, as in numpy)."""
        if self.ndim < 2:
            return self
        return Expr("transpose", (self,), self.shape[::-1], self.curvature, self.has_var)

    def __getitem__(self, key: object) -> Expr:
        try:
            shape = np.shape(_ghost(self.shape)[key])
        except (IndexError, TypeError, ValueError) as exc:
            raise ShapeError(f"synthesis: {self.describe()}[{key!r}]", f"an index into shape "
                             f"{self.shape}", key, what="index") from exc
        return Expr("index", (self,), shape, self.curvature, self.has_var, data=key)

    # -- constraints ------------------------------------------------------------------------
    def __eq__(self, other: object) -> Constraint:  # type: ignore[override]
        return Constraint("==", self, as_expr(other))

    def __le__(self, other: object) -> Constraint:
        return Constraint("<=", self, as_expr(other))

    def __ge__(self, other: object) -> Constraint:
        return Constraint("<=", as_expr(other), self)

    def __rshift__(self, other: object) -> Constraint:
        return Constraint(">>", self, as_expr(other))

    def __rrshift__(self, other: object) -> Constraint:
        return Constraint(">>", as_expr(other), self)

    def __lshift__(self, other: object) -> Constraint:
        return Constraint(">>", as_expr(other), self)

    def __rlshift__(self, other: object) -> Constraint:
        return Constraint(">>", self, as_expr(other))


def as_expr(value: object) -> Expr:
    """``value`` as an :class:`Expr` (numbers and arrays become constants)."""
    if isinstance(value, Expr):
        return value
    if isinstance(value, Constraint):
        raise BalustradeError("synthesis: a constraint is not an expression (did you chain "
                              "two comparisons?)")
    if _is_sparse(value):
        if not np.all(np.isfinite(value.data)):
            raise BalustradeError(f"synthesis: a sparse constant of shape {value.shape} has "
                                  "non-finite entries")
        return Expr("constant", (), value.shape, "constant", False, data=value.tocsr())
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise BalustradeError(f"synthesis: cannot use {type(value).__name__} in an expression "
                              "(numbers, numpy arrays and synthesis expressions only)") from None
    if not np.all(np.isfinite(arr)):
        raise BalustradeError(f"synthesis: a constant of shape {arr.shape} has non-finite "
                              "entries")
    return Expr("constant", (), arr.shape, "constant", False, data=arr)


def _is_sparse(value: object) -> bool:
    """Whether ``value`` is a scipy sparse matrix (kept sparse as a constant)."""
    return hasattr(value, "tocsr") and hasattr(value, "nnz")


def _scale(a: Expr, b: Expr) -> Expr:
    """``a * b`` with one side a scalar (use ``@`` for matrix products)."""
    if not (a.is_scalar or b.is_scalar):
        raise ShapeError(f"synthesis: {a.describe()} * {b.describe()}", "one scalar factor "
                         "(use @ for matrix products)", (a.shape, b.shape), what="shapes")
    scalar, other = (a, b) if a.is_scalar else (b, a)
    shape = other.shape if scalar.ndim == 0 or other.ndim else scalar.shape
    return Expr("mul", (a, b), shape, _product_curvature(a, b, scalar), a.has_var or b.has_var)


def _product_curvature(a: Expr, b: Expr, scalar: Expr) -> str:
    if a.has_var and b.has_var:
        raise ConvexityError(f"synthesis: {a.describe()} * {b.describe()} multiplies two "
                             "variable expressions: not affine, refused")
    if a.curvature in ("constant", "affine") and b.curvature in ("constant", "affine"):
        return "affine" if a.has_var or b.has_var else "constant"
    # a convex/concave factor times a number keeps or flips its curvature
    curved, factor = (a, b) if a.curvature in ("convex", "concave") else (b, a)
    if factor.op == "constant" and factor.is_scalar:
        value = float(np.asarray(factor.data).reshape(-1)[0])
        return curved.curvature if value >= 0 else _FLIP[curved.curvature]
    raise ConvexityError(f"synthesis: {curved.describe()} ({curved.curvature}) times "
                         f"{factor.describe()}: only a constant number may scale a "
                         "convex or concave expression")


def _matmul(a: Expr, b: Expr) -> Expr:
    if a.ndim == 0 or b.ndim == 0:
        raise ShapeError(f"synthesis: {a.describe()} @ {b.describe()}", "no scalar operand "
                         "(use * for scalars)", (a.shape, b.shape), what="shapes")
    try:
        shape = _matmul_shape(a.shape, b.shape)
    except ValueError:
        raise ShapeError(f"synthesis: {a.describe()} @ {b.describe()}", "matching inner "
                         "dimensions", (a.shape, b.shape), what="shapes") from None
    if a.has_var and b.has_var:
        raise ConvexityError(f"synthesis: {a.describe()} @ {b.describe()} multiplies two "
                             "variable expressions: not affine, refused")
    for e in (a, b):
        if e.curvature in ("convex", "concave", "unknown"):
            raise ConvexityError(f"synthesis: {e.describe()} ({e.curvature}) in a matrix "
                                 "product: only affine expressions may be multiplied")
    return Expr("matmul", (a, b), shape, "affine" if a.has_var or b.has_var else "constant",
                a.has_var or b.has_var)


def _affine(e: Expr, what: str) -> Expr:
    if e.curvature not in ("constant", "affine"):
        raise ConvexityError(f"synthesis: {what} needs an affine expression, "
                             f"{e.describe()} is {e.curvature}")
    return e


# -- functions --------------------------------------------------------------------------------
def reshape(e: object, shape: Sequence[int]) -> Expr:
    """``e`` reshaped (column-major, as in the thesis' ``vec``)."""
    e = as_expr(e)
    shape = tuple(int(s) for s in shape)
    if int(np.prod(shape)) != e.size:
        raise ShapeError(f"synthesis: reshape({e.describe()})", f"{e.size} entries", shape,
                         what="shape")
    if e.op == "constant":
        return as_expr(np.reshape(e.data, shape, order="F"))
    return Expr("reshape", (e,), shape, e.curvature, e.has_var, data=shape)


def _block(value: object, where: str) -> Expr:
    e = _affine(as_expr(value), where)
    if e.ndim < 2 and e.size == 1:
        return reshape(e, (1, 1))
    if e.ndim != 2:
        raise ShapeError(f"synthesis: {where}", "a matrix (2-D; write a row as a[None, :] or "
                         "reshape it)", e.shape, what="block shape")
    return _affine(e, where)


def bmat(blocks: Sequence[Sequence[object]]) -> Expr:
    """The block matrix ``[[B_11, B_12, …], [B_21, …], …]``; numbers are 1×1 blocks."""
    rows = [[_block(b, f"bmat block ({i}, {j})") for j, b in enumerate(row)]
            for i, row in enumerate(blocks)]
    if not rows or not all(rows):
        raise BalustradeError("synthesis: bmat needs a nonempty list of nonempty rows")
    if len({len(r) for r in rows}) != 1:
        raise ShapeError("synthesis: bmat", "rows with the same number of blocks",
                         [len(r) for r in rows], what="row lengths")
    for i, row in enumerate(rows):
        for j, b in enumerate(row):
            if b.shape[0] != row[0].shape[0] or b.shape[1] != rows[0][j].shape[1]:
                raise ShapeError(f"synthesis: bmat block ({i}, {j})",
                                 (row[0].shape[0], rows[0][j].shape[1]), b.shape)
    shape = (sum(r[0].shape[0] for r in rows), sum(b.shape[1] for b in rows[0]))
    has_var = any(b.has_var for r in rows for b in r)
    return Expr("bmat", tuple(tuple(r) for r in rows), shape,
                "affine" if has_var else "constant", has_var, label="bmat")


def _stack(op: str, items: Sequence[object]) -> Expr:
    exprs = tuple(as_expr(b) for b in items)
    if not exprs:
        raise BalustradeError(f"synthesis: {op} needs at least one item")
    for e in exprs:
        _affine(e, op)
    fn = np.hstack if op == "hstack" else np.vstack
    try:
        shape = np.shape(fn([_ghost(e.shape) for e in exprs]))
    except ValueError:
        raise ShapeError(f"synthesis: {op}", "compatible shapes",
                         [e.shape for e in exprs], what="shapes") from None
    has_var = any(e.has_var for e in exprs)
    return Expr(op, exprs, shape, "affine" if has_var else "constant", has_var)


def hstack(items: Sequence[object]) -> Expr:
    """``[B_1, B_2, …]`` side by side (numpy's ``hstack`` rules)."""
    return _stack("hstack", items)


def vstack(items: Sequence[object]) -> Expr:
    """``[B_1; B_2; …]`` on top of each other (numpy's ``vstack`` rules: 1-D items are
    rows)."""
    return _stack("vstack", items)


def diag(e: object) -> Expr:
    """The diagonal matrix of a vector, or the diagonal (vector) of a square matrix."""
    e = _affine(as_expr(e), "diag")
    if e.ndim == 1:
        shape: Shape = (e.shape[0], e.shape[0])
    elif e.ndim == 2 and e.shape[0] == e.shape[1]:
        shape = (e.shape[0],)
    else:
        raise ShapeError(f"synthesis: diag({e.describe()})", "a vector or a square matrix",
                         e.shape)
    return Expr("diag", (e,), shape, e.curvature, e.has_var)


def multiply(a: object, b: object) -> Expr:
    """The elementwise product of ``a`` and ``b`` (at most one with variables)."""
    a, b = as_expr(a), as_expr(b)
    try:
        shape = np.broadcast_shapes(a.shape, b.shape)
    except ValueError:
        raise ShapeError(f"synthesis: multiply({a.describe()}, {b.describe()})", "broadcastable "
                         "shapes", (a.shape, b.shape), what="shapes") from None
    if a.has_var and b.has_var:
        raise ConvexityError(f"synthesis: multiply({a.describe()}, {b.describe()}) multiplies "
                             "two variable expressions: not affine, refused")
    _affine(a, "multiply")
    _affine(b, "multiply")
    has_var = a.has_var or b.has_var
    return Expr("multiply", (a, b), shape, "affine" if has_var else "constant", has_var)


def sum_squares(e: object) -> Expr:
    """``‖e‖²`` (sum of squared entries): convex."""
    e = _affine(as_expr(e), "sum_squares")
    return Expr("sum_squares", (e,), (), "convex", e.has_var)


def trace(e: object) -> Expr:
    """``tr(M)`` of a square matrix."""
    e = as_expr(e)
    if e.ndim != 2 or e.shape[0] != e.shape[1]:
        raise ShapeError(f"synthesis: trace({e.describe()})", "a square matrix", e.shape)
    return Expr("trace", (e,), (), e.curvature, e.has_var)


def total(e: object) -> Expr:
    """The sum of all entries."""
    e = as_expr(e)
    return Expr("sum", (e,), (), e.curvature, e.has_var)


def norm(e: object, p: int | str = 2) -> Expr:
    """``‖e‖₂`` of a vector (``p = 2``; ``"fro"`` for the Frobenius norm of a matrix): convex.
    ``norm(x) <= t`` is a second-order cone."""
    e = _affine(as_expr(e), "norm")
    if p not in (2, "fro"):
        raise BalustradeError(f"synthesis: norm order {p!r}; use 2 or 'fro'")
    if p == 2 and e.ndim == 2 and 1 not in e.shape:
        raise ShapeError(f"synthesis: norm({e.describe()})", "a vector (use p='fro' for a "
                         "matrix)", e.shape)
    return Expr("norm", (e,), (), "convex", e.has_var, data=p)


def logdet(e: object) -> Expr:
    """``log det M`` of a symmetric matrix: concave (maximize it, or minimize its negative)."""
    e = _affine(as_expr(e), "logdet")
    if e.ndim != 2 or e.shape[0] != e.shape[1]:
        raise ShapeError(f"synthesis: logdet({e.describe()})", "a square matrix", e.shape)
    return Expr("logdet", (e,), (), "concave", e.has_var)


# -- constraints ------------------------------------------------------------------------------
class Constraint:
    """``lhs == rhs``, ``lhs <= rhs`` (elementwise), ``lhs ⪰ rhs`` (``">>"``), or the cones
    ``‖slice of lhs‖₂ <= rhs`` along ``axis`` (``"soc"``)."""

    __hash__ = object.__hash__

    def __init__(self, kind: str, lhs: Expr, rhs: Expr, axis: int | None = None):
        self.kind, self.lhs, self.rhs, self.axis = kind, lhs, rhs, axis
        text = f"{lhs.describe()} {kind} {rhs.describe()}"
        if kind == "==":
            _affine(lhs, f"equality {text}")
            _affine(rhs, f"equality {text}")
        elif kind == "<=":
            if lhs.curvature not in ("constant", "affine", "convex") \
                    or rhs.curvature not in ("constant", "affine", "concave"):
                raise ConvexityError(f"synthesis: {text} needs convex <= concave, got "
                                     f"{lhs.curvature} <= {rhs.curvature}")
        elif kind == ">>":
            _affine(lhs, f"LMI {text}")
            _affine(rhs, f"LMI {text}")
            for side in (lhs, rhs):
                if side.op == "constant" and side.size == 1 and float(side.data) == 0:
                    continue
                if side.ndim != 2 or side.shape[0] != side.shape[1]:
                    raise ShapeError(f"synthesis: LMI {text}", "square matrices", side.shape)
            if lhs.ndim == 2 and rhs.ndim == 2 and lhs.shape != rhs.shape:
                raise ShapeError(f"synthesis: LMI {text}", lhs.shape, rhs.shape)
        elif kind != "soc":  # "soc": ‖lhs slices‖₂ <= rhs, checked by SynthesisProblem.soc
            raise BalustradeError(f"synthesis: unknown constraint kind {kind!r}")
        if not (lhs.has_var or rhs.has_var):
            raise BalustradeError(f"synthesis: {text} involves no variable")
        if kind in ("==", "<="):
            try:
                np.broadcast_shapes(lhs.shape, rhs.shape)
            except ValueError:
                raise ShapeError(f"synthesis: {text}", lhs.shape, rhs.shape) from None

    def __bool__(self) -> bool:
        raise BalustradeError("synthesis: a constraint has no truth value; add it with "
                              "SynthesisProblem.subject_to(name, constraint)")

    def __repr__(self) -> str:
        return f"Constraint({self.lhs.describe()} {self.kind} {self.rhs.describe()})"


# -- the problem ------------------------------------------------------------------------------
class SynthesisProblem:
    """A convex synthesis problem (SDP/SOCP/LP) written with matrix variables and named blocks.

    Declare variables (:meth:`matrix`, :meth:`vector`, :meth:`scalar`) and parameters
    (:meth:`parameter`), add named constraint blocks (:meth:`lmi`, :meth:`soc`,
    :meth:`subject_to`) and one objective (:meth:`minimize`/:meth:`maximize`; none is a
    feasibility problem). Compile with :func:`balustrade.backends.compile_synthesis`.
    """

    def __init__(self, name: str = "SDP"):
        self.name = check_name(name, "SynthesisProblem: name")
        self.variables: dict[str, VariableDecl] = {}
        self.parameters: dict[str, ParameterDecl] = {}
        self.constraints: dict[str, Constraint] = {}
        self.sense: str = "minimize"
        self.objective: Expr | None = None
        self._exprs: dict[str, Expr] = {}

    def __repr__(self) -> str:
        return (f"SynthesisProblem({self.name!r}: {len(self.variables)} variables, "
                f"{len(self.parameters)} parameters, {len(self.constraints)} constraints)")

    # -- declarations ----------------------------------------------------------------------
    def _declare(self, name: str, what: str) -> str:
        name = check_name(name, f"{self.name}: {what} name")
        if name in self._exprs:
            raise BalustradeError(f"{self.name}: the name {name!r} is already declared")
        return name

    def matrix(self, name: str, shape: Sequence[int], symmetric: bool = False,
               psd: bool = False, nonneg: bool = False) -> Expr:
        """A matrix variable of ``shape``; ``symmetric=True`` for ``M = Mᵀ``, ``psd=True``
        for ``M ⪰ 0`` (implies symmetric), ``nonneg=True`` for entrywise ``M >= 0``."""
        name = self._declare(name, "variable")
        shape = _check_shape(shape, f"{self.name}: variable {name!r}")
        if (symmetric or psd) and (len(shape) != 2 or shape[0] != shape[1]):
            raise ShapeError(f"{self.name}: variable {name!r}", "a square shape for a "
                             "symmetric/PSD matrix", shape)
        if psd and nonneg:
            raise BalustradeError(f"{self.name}: variable {name!r}: psd and nonneg together "
                                  "are not supported; add the second as a constraint")
        decl = VariableDecl(name, shape, bool(symmetric or psd), bool(psd), bool(nonneg))
        self.variables[name] = decl
        expr = Expr("variable", (), shape, "affine", True, data=decl)
        self._exprs[name] = expr
        return expr

    def vector(self, name: str, size: int, nonneg: bool = False) -> Expr:
        """A vector variable of ``size`` entries."""
        return self.matrix(name, (size,), nonneg=nonneg)

    def scalar(self, name: str, nonneg: bool = False) -> Expr:
        """A scalar variable."""
        return self.matrix(name, (), nonneg=nonneg)

    def parameter(self, name: str, shape: Sequence[int] = (), value: object = None,
                  nonneg: bool = False, symmetric: bool = False, psd: bool = False) -> Expr:
        """Data that can change between solves without rebuilding (``value``: default)."""
        name = self._declare(name, "parameter")
        shape = _check_shape(shape, f"{self.name}: parameter {name!r}")
        decl = ParameterDecl(name, shape, None, bool(nonneg), bool(symmetric or psd),
                             bool(psd))
        if value is not None:
            decl.value = check_parameter_value(decl, value, self.name)
        self.parameters[name] = decl
        expr = Expr("parameter", (), shape, "affine", False, data=decl)
        self._exprs[name] = expr
        return expr

    def __getitem__(self, name: str) -> Expr:
        """The expression of a declared variable or parameter."""
        if name not in self._exprs:
            raise BalustradeError(f"{self.name}: no variable or parameter named {name!r}")
        return self._exprs[name]

    # -- constraints ------------------------------------------------------------------------
    def subject_to(self, name: str, constraint: Constraint) -> Constraint:
        """Add ``constraint`` (built with ``==``, ``<=``, ``>=``, ``>>``, ``<<``) as the
        block ``name``."""
        name = check_name(name, f"{self.name}: constraint name")
        if name in self.constraints:
            raise BalustradeError(f"{self.name}: a constraint named {name!r} already exists")
        if not isinstance(constraint, Constraint):
            raise BalustradeError(f"{self.name}: constraint {name!r} must be built with ==, "
                                  f"<=, >=, >> or <<, got {type(constraint).__name__}")
        self.constraints[name] = constraint
        return constraint

    def lmi(self, name: str, M: Expr | Constraint, symmetrize: bool = False) -> Constraint:
        """The LMI block ``M ⪰ 0`` (``M`` square, affine; or a constraint ``M >> N`` /
        ``M << N``). ``M`` must be symmetric for every value of the variables and
        parameters — checked at a random point, since a solver would silently constrain the
        symmetric part of a mistyped block; ``symmetrize=True`` imposes ``(M + Mᵀ)/2 ⪰ 0``
        instead (for a block symmetric only up to rounding)."""
        if isinstance(M, Constraint):
            if M.kind != ">>":
                raise BalustradeError(f"{self.name}: lmi {name!r} needs a matrix or a >> / << "
                                      f"constraint, got {M.kind}")
            c = M
        else:
            c = as_expr(M) >> 0
        if symmetrize:
            D = c.lhs - c.rhs
            c = Constraint(">>", 0.5 * (D + D.T), as_expr(0.0))
        else:
            _check_symmetric(f"{self.name}: lmi {name!r}", c)
        return self.subject_to(name, c)

    def soc(self, name: str, x: object, t: object, axis: int | None = None) -> Constraint:
        """The second-order cone ``‖x‖₂ <= t``; with ``axis``, one cone per slice of the matrix
        ``x`` (``axis=1``: ``‖x[i, :]‖₂ <= t[i]`` for every row ``i``; ``axis=0``: columns)."""
        if axis is None:
            return self.subject_to(name, norm(x) <= t)
        x, t = _affine(as_expr(x), f"soc {name!r}"), _affine(as_expr(t), f"soc {name!r}")
        if x.ndim != 2 or axis not in (0, 1):
            raise ShapeError(f"{self.name}: soc {name!r}", "a matrix x and axis 0 or 1",
                             (x.shape, axis), what="(shape, axis)")
        count = x.shape[1 - axis]
        if t.size != count or t.ndim > 1:
            raise ShapeError(f"{self.name}: soc {name!r} bounds t", (count,), t.shape)
        return self.subject_to(name, Constraint("soc", x, t, axis=axis))

    # -- objective ----------------------------------------------------------------------------
    def minimize(self, expr: object) -> None:
        """Minimize a scalar convex (or affine) expression."""
        self._objective(as_expr(expr), "minimize", ("constant", "affine", "convex"))

    def maximize(self, expr: object) -> None:
        """Maximize a scalar concave (or affine) expression, e.g. ``logdet(E)``."""
        self._objective(as_expr(expr), "maximize", ("constant", "affine", "concave"))

    def _objective(self, expr: Expr, sense: str, allowed: tuple[str, ...]) -> None:
        if expr.size != 1:
            raise ShapeError(f"{self.name}: objective", "a scalar", expr.shape)
        if expr.curvature not in allowed:
            raise ConvexityError(f"{self.name}: cannot {sense} {expr.describe()} "
                                 f"({expr.curvature})")
        self.sense, self.objective = sense, expr

    # -- checking a point without the solver (Principle 3) -------------------------------
    def violations(self, values: Mapping[str, object],
                   params: Mapping[str, object] | None = None) -> dict[str, float]:
        """How much each constraint block is violated at ``values`` (variables by name;
        ``params`` by name, declared defaults otherwise), evaluated with numpy alone:
        ``max(lhs − rhs)`` for ``<=``, ``max |lhs − rhs|`` for ``==``, ``−λ_min`` of the
        symmetric part for an LMI, ``max(‖x_i‖ − t_i)`` for a cone; ``<= 0`` means
        satisfied (the declared attributes nonneg/PSD of the variables are blocks
        ``"attribute of NAME"``)."""
        env = self._environment(values, params)
        out: dict[str, float] = {}
        for name, d in self.variables.items():
            v = env[name]
            if d.nonneg:
                out[f"attribute of {name}"] = float(np.max(-v, initial=-np.inf))
            if d.psd:
                out[f"attribute of {name}"] = -float(np.min(np.linalg.eigvalsh(
                    0.5 * (v + v.T))))
            if d.symmetric:
                out[f"symmetry of {name}"] = float(np.max(np.abs(v - v.T)))
        for name, c in self.constraints.items():
            out[name] = _violation(c, env)
        return out

    def value(self, expr: Expr, values: Mapping[str, object],
              params: Mapping[str, object] | None = None) -> np.ndarray:
        """``expr`` evaluated with numpy at ``values`` (and ``params``)."""
        return evaluate(expr, self._environment(values, params))

    def _environment(self, values: Mapping[str, object],
                     params: Mapping[str, object] | None) -> dict[str, np.ndarray]:
        env: dict[str, np.ndarray] = {}
        for name, d in self.variables.items():
            if name not in values:
                raise BalustradeError(f"{self.name}: no value for variable {name!r}")
            v = np.asarray(values[name], dtype=float)
            if v.shape != d.shape:
                raise ShapeError(f"{self.name}: value of {name!r}", d.shape, v.shape)
            env[name] = v
        params = dict(params or {})
        for name, d in self.parameters.items():
            value = params.get(name, d.value)
            if value is None:
                raise BalustradeError(f"{self.name}: parameter {name!r} has no value")
            env[name] = check_parameter_value(d, value, self.name)
        return env


def _check_shape(shape: object, block: str) -> Shape:
    if isinstance(shape, int | np.integer):
        shape = (int(shape),)
    try:
        out = tuple(int(s) for s in shape)  # type: ignore[union-attr]
    except TypeError:
        raise ShapeError(block, "a tuple of sizes", shape, what="shape") from None
    if len(out) > 2 or any(s < 1 for s in out):
        raise ShapeError(block, "at most two positive sizes", out, what="shape")
    return out


def check_parameter_value(decl: ParameterDecl, value: object, problem: str) -> np.ndarray:
    """``value`` as an array of ``decl``'s shape, finite and of the declared sign/structure."""
    block = f"{problem}: parameter {decl.name!r}"
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise BalustradeError(f"{block}: expected numbers, got {type(value).__name__}") from None
    if arr.shape != decl.shape:
        if arr.size == int(np.prod(decl.shape)) and (arr.ndim <= 1 or len(decl.shape) <= 1):
            arr = arr.reshape(decl.shape)
        else:
            raise ShapeError(block, decl.shape, arr.shape)
    if not np.all(np.isfinite(arr)):
        raise BalustradeError(f"{block}: non-finite value")
    if decl.nonneg and np.any(arr < 0):
        raise BalustradeError(f"{block}: declared nonneg, got a negative entry")
    if decl.symmetric and not np.allclose(arr, arr.T, rtol=0, atol=1e-12):
        raise BalustradeError(f"{block}: declared symmetric, got a nonsymmetric matrix")
    if decl.psd and np.min(np.linalg.eigvalsh(0.5 * (arr + arr.T))) < -1e-12:
        raise BalustradeError(f"{block}: declared PSD, got a negative eigenvalue")
    return arr


# -- numeric evaluation (no solver) --------------------------------------------------------------
def add_terms(e: Expr) -> list[Expr]:
    """The terms of a (left-nested) sum, in order, without recursion (``sum(...)`` of many
    terms nests deeply)."""
    terms: list[Expr] = []
    stack = [e]
    while stack:
        node = stack.pop()
        if node.op == "add":
            stack.extend(reversed(node.args))
        else:
            terms.append(node)
    return terms


def leaves(e: Expr) -> Iterator[Expr]:
    """The variables and parameters of ``e`` (each node visited once)."""
    seen: set[int] = set()
    stack = [e]
    while stack:
        node = stack.pop()
        if id(node) in seen:
            continue
        seen.add(id(node))
        if node.op in ("variable", "parameter"):
            yield node
        elif node.op == "bmat":
            stack.extend(b for row in node.args for b in row)
        else:
            stack.extend(a for a in node.args if isinstance(a, Expr))


def _dense(x: object) -> np.ndarray:
    if _is_sparse(x):
        return np.asarray(x.toarray())
    return np.asarray(x, dtype=float)


def evaluate(e: Expr, env: Mapping[str, np.ndarray]) -> np.ndarray:
    """``e`` as a numpy array, with variables and parameters taken from ``env`` by name."""
    memo: dict[int, np.ndarray] = {}

    def ev(node: Expr) -> np.ndarray:
        key = id(node)
        if key not in memo:
            memo[key] = _dense(_eval_node(node, ev, env))
        return memo[key]

    return ev(e)


def _eval_node(e: Expr, ev, env: Mapping[str, np.ndarray]) -> object:
    op = e.op
    if op in ("variable", "parameter"):
        return env[e.data.name]
    if op == "constant":
        return e.data
    if op == "add":
        first, *rest = add_terms(e)
        out = ev(first)
        for t in rest:
            out = out + ev(t)
        return out
    if op == "bmat":
        return np.block([[ev(b) for b in row] for row in e.args])
    if op == "matmul":
        a, b = e.args
        return (a.data if a.op == "constant" else ev(a)) @ (
            b.data if b.op == "constant" else ev(b))
    x = [ev(a) for a in e.args]
    simple = {
        "neg": lambda: -x[0], "mul": lambda: x[0] * x[1], "div": lambda: x[0] / x[1],
        "transpose": lambda: x[0].T, "index": lambda: x[0][e.data],
        "reshape": lambda: np.reshape(x[0], e.data, order="F"),
        "trace": lambda: np.trace(x[0]), "sum": lambda: np.sum(x[0]),
        "hstack": lambda: np.hstack(x), "vstack": lambda: np.vstack(x),
        "diag": lambda: np.diag(x[0]), "multiply": lambda: x[0] * x[1],
        "sum_squares": lambda: np.sum(x[0] ** 2),
        "norm": lambda: np.linalg.norm(np.ravel(x[0])),
        "logdet": lambda: _logdet(x[0]),
    }
    if op not in simple:
        raise BalustradeError(f"synthesis: no numeric evaluation for {op!r}")
    return simple[op]()


def _logdet(M: np.ndarray) -> float:
    sign, value = np.linalg.slogdet(0.5 * (M + M.T))
    return float(value) if sign > 0 else -np.inf


def _violation(c: Constraint, env: Mapping[str, np.ndarray]) -> float:
    lhs, rhs = evaluate(c.lhs, env), evaluate(c.rhs, env)
    if c.kind == "<=":
        return float(np.max(lhs - rhs))
    if c.kind == "==":
        return float(np.max(np.abs(lhs - rhs)))
    if c.kind == ">>":
        D = lhs - rhs
        return -float(np.min(np.linalg.eigvalsh(0.5 * (D + D.T))))
    norms = np.linalg.norm(lhs, axis=c.axis)   # "soc"
    return float(np.max(norms - np.ravel(rhs)))


def _random_value(shape: Shape, symmetric: bool, psd: bool, nonneg: bool,
                  rng: np.random.Generator) -> np.ndarray:
    v = rng.standard_normal(shape)
    if psd:
        return v @ v.T
    if symmetric:
        v = v + v.T
    return np.abs(v) if nonneg else v


def _check_symmetric(block: str, c: Constraint, tol: float = 1e-9) -> None:
    """Refuse an LMI whose matrix ``lhs − rhs`` is not symmetric at a random point of its
    variables and parameters (the matrix is affine in both, so one generic point tells)."""
    rng = np.random.default_rng(0)
    env = {}
    for side in (c.lhs, c.rhs):
        for leaf in leaves(side):
            d = leaf.data
            env[d.name] = _random_value(d.shape, d.symmetric, d.psd, d.nonneg, rng)
    D = evaluate(c.lhs, env) - evaluate(c.rhs, env)
    if D.ndim < 2:
        return
    gap = np.abs(D - D.T)
    worst = float(np.max(gap))
    if worst > tol * max(1.0, float(np.max(np.abs(D)))):
        i, j = np.unravel_index(int(np.argmax(gap)), gap.shape)
        raise BalustradeError(f"{block}: the matrix is not symmetric (entries ({i}, {j}) and "
                              f"({j}, {i}) differ at a random point of the variables); check "
                              "its off-diagonal blocks (a solver would silently constrain the "
                              "symmetric part), or pass symmetrize=True")


__all__ = ["CURVATURES", "Constraint", "Expr", "ParameterDecl", "SynthesisProblem",
           "VariableDecl", "add_terms", "as_expr", "bmat", "check_parameter_value", "diag",
           "evaluate", "hstack", "leaves", "logdet", "multiply", "norm", "reshape",
           "sum_squares", "total", "trace", "vstack"]
