"""Input validation shared by all layers: shapes, finiteness, signs, types, positive
semidefiniteness, and symbolic expressions that lost their symbols (``math.sin`` on CasADi)."""

from __future__ import annotations

import numbers

import casadi as ca
import numpy as np

from balustrade.errors import BalustradeError, NonFiniteError, NotPSDError, ShapeError


def as_float_array(value: object, block: str) -> np.ndarray:
    """``np.asarray(value, dtype=float)``, with a :class:`BalustradeError` naming ``block``
    instead of numpy's ``ValueError``/``TypeError`` for strings, ``None``, ragged lists and
    other non-numeric input (booleans, integers and floats are accepted)."""
    if isinstance(value, (str, bytes)) or value is None:
        raise BalustradeError(f"{block}: expected a number or an array of numbers, got "
                              f"{type(value).__name__} {value!r:.40}")
    if isinstance(value, (ca.SX, ca.MX)):
        raise BalustradeError(f"{block}: expected numbers, got a symbolic CasADi "
                              f"{type(value).__name__} of shape {value.shape}")
    try:
        raw = np.asarray(value)
        if raw.dtype == object:  # e.g. CasADi symbols in a list: float() would give NaN
            bad = [v for v in raw.reshape(-1) if not isinstance(v, numbers.Real)]
            if bad:
                raise TypeError(f"an entry of type {type(bad[0]).__name__}")
        elif raw.dtype.kind not in "biuf":
            raise TypeError(f"an array of dtype {raw.dtype}")
        arr = raw.astype(float)
    except (TypeError, ValueError) as exc:
        raise BalustradeError(f"{block}: expected a number or an array of numbers, got "
                              f"{type(value).__name__} ({exc})") from exc
    return arr


def as_matrix(value: object, block: str, shape: tuple[int | None, int | None] | None = None,
              finite: bool = True) -> np.ndarray:
    """Return ``value`` as a 2-D float array, checking its shape (``None`` = any size)."""
    arr = as_float_array(value, block)
    if arr.ndim == 0:
        arr = arr.reshape(1, 1)
    elif arr.ndim == 1:
        arr = arr.reshape(-1, 1) if shape is None or shape[1] in (1, None) else arr.reshape(1, -1)
    if arr.ndim != 2:
        raise ShapeError(block, "a 2-D matrix", f"an array with shape {arr.shape}")
    if shape is not None:
        for want, got in zip(shape, arr.shape):
            if want is not None and want != got:
                raise ShapeError(block, _fmt(shape), arr.shape, what="shape")
    if finite and not np.all(np.isfinite(arr)):
        raise NonFiniteError(f"{block}: contains NaN or inf (shape {arr.shape})")
    return arr


def as_vector(value: object, block: str, size: int | None = None,
              finite: bool = True) -> np.ndarray:
    """Return ``value`` as a 1-D float array of length ``size`` (a column or row is flattened)."""
    arr = as_float_array(value, block)
    if arr.ndim == 2 and 1 in arr.shape:
        arr = arr.reshape(-1)
    elif arr.ndim == 0:
        arr = arr.reshape(1)
    if arr.ndim != 1:
        raise ShapeError(block, f"a vector of length {size if size is not None else 'n'}",
                         f"an array with shape {arr.shape}")
    if size is not None and arr.size != size:
        raise ShapeError(block, (size,), arr.shape)
    if finite and not np.all(np.isfinite(arr)):
        raise NonFiniteError(f"{block}: contains NaN or inf: {arr}")
    return arr


def check_psd(M: np.ndarray, block: str, strict: bool = False, tol: float = 1e-9) -> np.ndarray:
    """Check that ``M`` is symmetric positive semidefinite (definite if ``strict``)."""
    M = as_matrix(M, block)
    if M.shape[0] != M.shape[1]:
        raise ShapeError(block, "a square matrix", M.shape)
    scale = max(1.0, float(np.max(np.abs(M))))
    if not np.allclose(M, M.T, atol=tol * scale):
        raise NotPSDError(f"{block}: matrix of shape {M.shape} is not symmetric")
    sym = 0.5 * M + 0.5 * M.T  # no overflow near the largest floats
    lam_min = float(np.min(np.linalg.eigvalsh(sym)))
    if lam_min < -tol * scale or (strict and lam_min <= tol * scale):
        kind = "positive definite" if strict else "positive semidefinite"
        raise NotPSDError(f"{block}: matrix of shape {M.shape} is not {kind} "
                          f"(smallest eigenvalue {lam_min:.3g})")
    return sym


def as_scalar(value: object, block: str, low: float | None = None, high: float | None = None,
              low_open: bool = False, high_open: bool = False) -> float:
    """A finite real number in ``[low, high]`` (``(low, ...`` if ``low_open``, ``..., high)``
    if ``high_open``); the message names ``block`` and the allowed range."""
    if isinstance(value, bool) or not isinstance(value, (numbers.Real, np.ndarray, ca.DM)):
        raise BalustradeError(f"{block}: expected a real number, got {type(value).__name__} "
                              f"{value!r:.40}")
    arr = as_float_array(value, block)
    if arr.size != 1:
        raise ShapeError(block, "a scalar", arr.shape)
    x = float(arr.reshape(-1)[0])
    if not np.isfinite(x):
        raise NonFiniteError(f"{block}: must be finite, got {x}")
    too_low = low is not None and (x <= low if low_open else x < low)
    too_high = high is not None and (x >= high if high_open else x > high)
    if too_low or too_high:
        lo = "-inf" if low is None else f"{low:g}"
        hi = "inf" if high is None else f"{high:g}"
        left = "(" if low_open or low is None else "["
        right = ")" if high_open or high is None else "]"
        rng = f"{left}{lo}, {hi}{right}"
        raise BalustradeError(f"{block}: must lie in {rng}, got {x:g}")
    return x


def as_count(value: object, block: str, low: int = 0) -> int:
    """An integer ``>= low`` (a dimension, a horizon, a number of steps); ``bool`` and
    non-integral floats are refused."""
    if isinstance(value, bool) or not isinstance(value, (numbers.Integral, np.integer)):
        raise BalustradeError(f"{block}: expected an integer >= {low}, got "
                              f"{type(value).__name__} {value!r:.40}")
    if int(value) < low:
        raise BalustradeError(f"{block}: expected an integer >= {low}, got {int(value)}")
    return int(value)


def check_name(name: object, block: str) -> str:
    """A symbol or block name: a string."""
    if not isinstance(name, str):
        raise BalustradeError(f"{block}: a name must be a string, got {type(name).__name__} "
                              f"{name!r:.40}")
    return name


def check_callable(f: object, block: str) -> None:
    """A user function (dynamics, constraint function, CBF)."""
    if not callable(f):
        raise BalustradeError(f"{block}: expected a callable, got {type(f).__name__} "
                              f"{f!r:.40}")


def nan_constants(expr: ca.SX) -> bool:
    """Whether the symbolic ``expr`` contains a NaN constant — what ``math.sin(x)``,
    ``float(x)`` or ``np.asarray(x, dtype=float)`` leave of a CasADi symbol ``x``."""
    if not isinstance(expr, ca.SX):  # the copy costs ~20 us
        expr = ca.SX(expr)
    if expr.numel() == 0 or expr.is_valid_input():  # only symbols (the usual cost and
        return False                                  # slack arguments): no constant at all
    if expr.is_constant():
        return bool(np.any(np.isnan(np.asarray(ca.DM(expr), dtype=float))))
    fun = ca.Function("nan_scan", ca.symvar(expr), [expr])
    return any(fun.instruction_id(k) == ca.OP_CONST and np.isnan(fun.instruction_constant(k))
               for k in range(fun.n_instructions()))


SYMBOL_LOST = ("a function converted a CasADi symbol to a float (math.sin(x), float(x), "
               "np.asarray(x, dtype=float) and the like give NaN); use CasADi's functions "
               "(ca.sin, ca.cos, ca.exp, ca.sqrt, ca.fabs, ca.fmax, ...) or build the model "
               "with System.from_sympy")


def check_symbolic(expr: ca.SX, block: str) -> ca.SX:
    """Refuse an expression with NaN constants (see :func:`nan_constants`)."""
    if nan_constants(expr):
        raise NonFiniteError(f"{block}: the expression contains NaN: a NaN number was given, "
                             f"or {SYMBOL_LOST}")
    return expr


def _fmt(shape: tuple[int | None, ...]) -> str:
    return "(" + ", ".join("n" if s is None else str(s) for s in shape) + ")"


# -- arguments of the formulation builders (balustrade.problems) -------------------------------
def check_horizon(N: object, block: str) -> int:
    """A prediction horizon: an integer ``N >= 1``."""
    return as_count(N, f"{block}: horizon N", low=1)


def check_deltas(deltas: object, N: int, block: str) -> np.ndarray:
    """Tightenings ``Δ_0, …, Δ_{N−1}`` of SPEC §1.4: ``N`` finite nonnegative numbers (a
    scalar is repeated) with ``0 = Δ_0 < Δ_1 < … < Δ_{N−1}``.

    ``Δ_0 ≠ 0`` and a decreasing step ``Δ_{i+1} < Δ_i`` are refused: with them the candidate
    slack of (5.17) ``ξ̃_i = max(0, ξ*_{i+1} + (Δ_i − Δ_{i+1}))`` can exceed ``ξ*_{i+1}``, so
    ``h̃`` (§1.12) can increase and the PCBF decrease of Theorem 2.30 is lost (``Δ_0 ≠ 0``
    also moves the safe set ``{h_PB = 0}`` off ``{c_x(x) ≤ 0}``, SPEC §2.7 notes).
    An equal step ``Δ_{i+1} = Δ_i`` (e.g. all zeros, the untightened problem) keeps
    ``h̃`` non-increasing but not strictly decreasing: it is accepted with a
    :class:`~balustrade.errors.TighteningWarning`."""
    where = f"{block}: tightenings deltas (Δ_i)"
    arr = as_float_array(deltas, where)
    if arr.ndim == 0:
        arr = np.full(N, float(arr))
    d = as_vector(arr, where, N)
    if np.any(d < 0):
        raise BalustradeError(f"{where}: must be >= 0, got negative entries at steps "
                              f"{np.flatnonzero(d < 0).tolist()} ({d[d < 0]})")
    if d.size and d[0] != 0.0:
        raise BalustradeError(f"{where}: Δ_0 must be 0 (SPEC §1.4: 0 = Δ_0 < Δ_1 < …), got "
                              f"Δ_0 = {d[0]:g}" + (" (a scalar is repeated at every step; "
                                                  "use c * np.arange(N))"
                                                  if np.all(d == d[0]) else ""))
    steps = np.diff(d)
    if np.any(steps < 0):
        i = np.flatnonzero(steps < 0)
        raise BalustradeError(f"{where}: must increase (SPEC §1.4: Δ_0 < Δ_1 < …), got "
                              f"Δ_(i+1) < Δ_i at i = {i.tolist()} ({d[i]} -> {d[i + 1]}); "
                              f"the PCBF decrease (Theorem 2.30) needs increasing tightenings")
    if np.any(steps == 0):
        import warnings

        from balustrade.errors import TighteningWarning

        i = np.flatnonzero(steps == 0)
        warnings.warn(f"{where}: not strictly increasing (Δ_(i+1) = Δ_i at i = "
                      f"{i[:5].tolist()}{' …' if i.size > 5 else ''}); the slack cost is "
                      f"non-increasing but its strict decrease (SPEC §1.4, Theorem 2.30) is "
                      f"not guaranteed; SPEC's examples use Δ_i = i * c",
                      TighteningWarning, stacklevel=3)
    return d


def check_weight(M: object, n: int, block: str, strict: bool = False) -> np.ndarray:
    """A cost weight: an ``(n, n)`` symmetric positive (semi)definite matrix."""
    M = as_matrix(M, block)
    if M.shape != (n, n):
        raise ShapeError(block, (n, n), M.shape)
    return check_psd(M, block, strict=strict)


def check_norm_order(order: object, block: str) -> object:
    """A slack norm order: 1, 2 or inf."""
    if isinstance(order, bool) or not isinstance(order, (int, float, str)) \
            or order not in (1, 2, np.inf, "inf"):
        raise BalustradeError(f"{block}: norm order must be 1, 2 or inf, got {order!r}")
    return order


def check_instance(value: object, kind: type | tuple[type, ...], block: str) -> None:
    """``value`` is a ``kind`` (a System, a Set, a Polytope, ...)."""
    if not isinstance(value, kind):
        names = " or ".join(k.__name__ for k in (kind if isinstance(kind, tuple) else (kind,)))
        raise BalustradeError(f"{block}: expected a {names}, got {type(value).__name__}")
