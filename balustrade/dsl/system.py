"""Discrete-time dynamics ``x⁺ = f(x, u, w; θ)`` (SPEC §1.2, (2.1)).

A :class:`System` wraps one CasADi function ``f(x, u, w, theta)``; the horizon problem
builder and every backend call it on symbols, closed loops call :meth:`System.step` on
numbers. Construct it

* from a Python callable that works on CasADi symbols: ``System(f, nx=2, nu=1)``;
* from sympy expressions: :meth:`System.from_sympy`;
* for linear models: ``LinearSystem(A, B, E)``, ``x⁺ = A x + B u + E w`` ((2.4), (3.1), (6.9));
* from continuous-time models: :meth:`System.from_continuous` with Euler or RK4.

Arguments the model does not use (Remark 2.1) have size 0 and may be omitted in calls.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import casadi as ca
import numpy as np

from balustrade._checks import (
    SYMBOL_LOST,
    as_count,
    as_matrix,
    as_scalar,
    as_vector,
    check_callable,
    check_name,
    nan_constants,
)
from balustrade.errors import BalustradeError, NonFiniteError, ShapeError

Dynamics = Callable[..., object]


class System:
    """Discrete-time system ``x⁺ = f(x, u, w; θ)`` with shapes checked at construction.

    ``f`` is called with CasADi column symbols ``(x, u, w, theta)`` (only as many arguments
    as it accepts: ``f(x, u)``, ``f(x, u, w)`` or ``f(x, u, w, theta)``) and must return an
    expression with ``nx`` entries.
    """

    is_linear = False

    def __init__(self, f: Dynamics, nx: int, nu: int, nw: int = 0, ntheta: int = 0,
                 name: str = "system"):
        self.name = check_name(name, "System: name")
        self.nx = as_count(nx, f"{name}: nx (state dimension)", low=1)
        self.nu = as_count(nu, f"{name}: nu (input dimension)")
        self.nw = as_count(nw, f"{name}: nw (disturbance dimension)")
        self.ntheta = as_count(ntheta, f"{name}: ntheta (parameter dimension)")
        check_callable(f, f"{name}: dynamics f")
        x = ca.SX.sym("x", self.nx)
        u = ca.SX.sym("u", self.nu)
        w = ca.SX.sym("w", self.nw)
        th = ca.SX.sym("theta", self.ntheta)
        args = [x, u, w, th]
        n_args = _arity(f)
        try:
            out = f(*args[: max(n_args, 2)]) if n_args is not None else f(*args)
        except Exception as exc:  # the user's function failed on symbols
            raise BalustradeError(
                f"{name}: f(x, u, w, theta) failed on CasADi symbols with shapes "
                f"x ({self.nx}, 1), u ({self.nu}, 1), w ({self.nw}, 1), "
                f"theta ({self.ntheta}, 1): {exc} (use CasADi's functions on symbols: "
                "ca.sin, ca.fmax, ca.if_else, ...)") from exc
        try:
            out = ca.vec(ca.SX(out) if not isinstance(out, ca.SX) else out) \
                if not isinstance(out, (list, tuple)) else ca.vertcat(*out)
        except Exception as exc:  # e.g. a numpy object array or a string
            raise BalustradeError(f"{name}: f(x, u, w, theta) returned a "
                                  f"{type(out).__name__} that is not a CasADi expression "
                                  f"({exc}); return ca.vertcat(...) of the next state") from exc
        if out.numel() != self.nx:
            raise ShapeError(f"{name}: f(x, u, w, theta)", f"{self.nx} entries (nx)",
                             f"{out.numel()} entries (shape {out.shape})", what="output with")
        if nan_constants(out):
            rows = [i for i in range(self.nx) if nan_constants(out[i])]
            raise NonFiniteError(f"{name}: f(x, u, w, theta) evaluates to NaN in rows {rows} "
                                 f"on symbols: {SYMBOL_LOST}")
        self._f_expr = out
        self.function = ca.Function(name, [x, u, w, th], [out], ["x", "u", "w", "theta"],
                                    ["x_next"])

    # -- evaluation -------------------------------------------------------------------
    def __call__(self, x: object, u: object, w: object | None = None,
                 theta: object | None = None) -> object:
        """``f(x, u, w, θ)`` on symbols or numbers (missing ``w``/``θ`` are zero)."""
        w = ca.DM.zeros(self.nw) if w is None else w
        theta = ca.DM.zeros(self.ntheta) if theta is None else theta
        return self.function(x, u, w, theta)

    def step(self, x: np.ndarray, u: np.ndarray, w: np.ndarray | None = None,
             theta: np.ndarray | None = None) -> np.ndarray:
        """Numeric next state; checks shapes and finiteness of every argument."""
        x = as_vector(x, f"{self.name}.step: x", self.nx)
        u = as_vector(u, f"{self.name}.step: u", self.nu)
        w = np.zeros(self.nw) if w is None else as_vector(w, f"{self.name}.step: w", self.nw)
        theta = (np.zeros(self.ntheta) if theta is None
                 else as_vector(theta, f"{self.name}.step: theta", self.ntheta))
        return np.asarray(self.function(x, u, w, theta)).reshape(-1)

    def jacobians(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(∂f/∂x, ∂f/∂u)`` at ``(x, u, w=0)``: the linearization."""
        xs, us = ca.SX.sym("x", self.nx), ca.SX.sym("u", self.nu)
        fx = self(xs, us)
        jac = ca.Function("linearization", [xs, us], [ca.jacobian(fx, xs), ca.jacobian(fx, us)])
        A, B = jac(as_vector(x, f"{self.name}.jacobians: x", self.nx),
                   as_vector(u, f"{self.name}.jacobians: u", self.nu))
        return np.asarray(A), np.asarray(B)

    # -- constructors ----------------------------------------------------------------
    @classmethod
    def from_sympy(cls, exprs: Sequence[object], x: Sequence[object], u: Sequence[object],
                   w: Sequence[object] = (), theta: Sequence[object] = (),
                   name: str = "system") -> System:
        """Discrete dynamics from sympy expressions ``x⁺_i = exprs[i](x, u, w, θ)``."""
        import sympy

        name = check_name(name, "System.from_sympy: name")
        symbols = list(x) + list(u) + list(w) + list(theta)
        exprs = list(exprs)
        if len(exprs) != len(x):
            raise ShapeError(f"{name}: from_sympy", f"{len(x)} expressions (one per state)",
                             f"{len(exprs)} expressions", what="")
        free = set().union(*(sympy.sympify(e).free_symbols for e in exprs)) - set(symbols)
        if free:
            raise BalustradeError(f"{name}: from_sympy: expressions use symbols that are not "
                                  f"states, inputs, disturbances or parameters: "
                                  f"{sorted(map(str, free))}")
        lowered = sympy.lambdify(symbols, exprs, modules=[_SYMPY_TO_CASADI, "math"])
        nx, nu, nw, nth = len(x), len(u), len(w), len(theta)

        def f(xs: ca.SX, us: ca.SX, ws: ca.SX, ths: ca.SX) -> ca.SX:
            args = [xs[i] for i in range(nx)] + [us[i] for i in range(nu)]
            args += [ws[i] for i in range(nw)] + [ths[i] for i in range(nth)]
            return ca.vertcat(*lowered(*args))

        try:
            return cls(f, nx, nu, nw, nth, name=name)
        except NonFiniteError as exc:
            raise NonFiniteError(
                f"{name}: from_sympy: an expression lowers to NaN: it uses a sympy function "
                f"without a CasADi counterpart (supported: {', '.join(_SYMPY_TO_CASADI)}, "
                f"and +, -, *, /, **); rewrite it with these ({exc})") from exc

    @classmethod
    def from_continuous(cls, f_ct: Dynamics, nx: int, nu: int, dt: float,
                        method: str = "rk4", nw: int = 0, ntheta: int = 0,
                        steps: int = 1, name: str = "system") -> System:
        """Discretize ``ẋ = f_ct(x, u, w, θ)`` with explicit Euler or classic RK4.

        The input and disturbance are held constant over the sample (zero-order hold);
        ``steps`` sub-steps of length ``dt/steps`` are taken.
        """
        name = check_name(name, "System.from_continuous: name")
        if method not in ("euler", "rk4"):
            raise BalustradeError(f"{name}: unknown discretization {method!r}; "
                                  "use 'euler' or 'rk4'")
        dt = as_scalar(dt, f"{name}: sampling time dt", low=0.0, low_open=True)
        steps = as_count(steps, f"{name}: steps (sub-steps per sample)", low=1)
        ct = cls(f_ct, nx, nu, nw, ntheta, name=f"{name}_ct")
        h = dt / steps

        def f(x: ca.SX, u: ca.SX, w: ca.SX, th: ca.SX) -> ca.SX:
            for _ in range(steps):
                k1 = ct(x, u, w, th)
                if method == "euler":
                    x = x + h * k1
                    continue
                k2 = ct(x + h / 2 * k1, u, w, th)
                k3 = ct(x + h / 2 * k2, u, w, th)
                k4 = ct(x + h * k3, u, w, th)
                x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
            return x

        return cls(f, nx, nu, nw, ntheta, name=name)


class LinearSystem(System):
    """``x⁺ = A x + B u + E w`` ((2.4), (3.1), (6.9)); ``E`` defaults to ``I`` if ``nw`` given."""

    is_linear = True

    def __init__(self, A: object, B: object, E: object | None = None, name: str = "linear"):
        name = check_name(name, "LinearSystem: name")
        A = as_matrix(A, f"{name}: A")
        if A.shape[0] != A.shape[1]:
            raise ShapeError(f"{name}: A", "a square matrix (nx, nx)", A.shape)
        nx = A.shape[0]
        B = as_matrix(B, f"{name}: B", (nx, None))
        E = np.zeros((nx, 0)) if E is None else as_matrix(E, f"{name}: E", (nx, None))
        self.A, self.B, self.E = A, B, E
        Ad, Bd, Ed = ca.DM(A), ca.DM(B), ca.DM(E)

        def f(x: ca.SX, u: ca.SX, w: ca.SX) -> ca.SX:
            out = ca.mtimes(Ad, x) + ca.mtimes(Bd, u)
            return out + ca.mtimes(Ed, w) if E.shape[1] else out

        super().__init__(f, nx, B.shape[1], E.shape[1], 0, name=name)

    def step(self, x: np.ndarray, u: np.ndarray, w: np.ndarray | None = None,
             theta: np.ndarray | None = None) -> np.ndarray:
        x = as_vector(x, f"{self.name}.step: x", self.nx)
        u = as_vector(u, f"{self.name}.step: u", self.nu)
        out = self.A @ x + self.B @ u
        if w is not None and self.nw:
            out = out + self.E @ as_vector(w, f"{self.name}.step: w", self.nw)
        return out


def _arity(f: Dynamics) -> int | None:
    import inspect

    try:
        params = inspect.signature(f).parameters.values()
    except (TypeError, ValueError):
        return None
    if any(p.kind == p.VAR_POSITIONAL for p in params):
        return None
    return sum(1 for p in params if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)
               and p.default is p.empty) or None


_SYMPY_TO_CASADI = {
    "sin": ca.sin, "cos": ca.cos, "tan": ca.tan, "exp": ca.exp, "log": ca.log,
    "sqrt": ca.sqrt, "atan": ca.atan, "atan2": ca.atan2, "asin": ca.asin, "acos": ca.acos,
    "sinh": ca.sinh, "cosh": ca.cosh, "tanh": ca.tanh, "Abs": ca.fabs, "sign": ca.sign,
    "Max": ca.fmax, "Min": ca.fmin,
}
