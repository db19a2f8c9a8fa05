"""An explicit affine control law ``π(x) = K (x − x_s) + k``: the terminal policy ``π_f`` of
the candidate (5.17)/(6.14) of Algorithms 5.2/6.3/6.4 written so that Python and its
emitted C evaluate the same expression.

:class:`AffinePolicy` is called like the numpy policy it replaces (``pi_f(x)`` on a state of
``n`` entries returns ``m`` inputs) and also on CasADi symbols, so the tube functions
(:mod:`balustrade.control.tube_functions`) build the candidate from it symbolically and
:mod:`balustrade.codegen.emit_robust` generates the C from that same expression: C and
Python compute the same candidate by construction. A numpy-only callable cannot be
emitted (it has no expression to generate; issue #14, session 13, docs/vehicles.md).

E.g. the terminal CBF's ``π_f(x) = K x`` is ``AffinePolicy(cbf.K)``; a CBF about a
steady state ``x_s`` with ``π_f(x) = K (x − x_s)`` is ``AffinePolicy(cbf.K, x_s=cbf.x_s)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from balustrade._checks import as_matrix, as_vector
from balustrade.errors import BalustradeError


@dataclass(frozen=True)
class AffinePolicy:
    """``π(x) = K (x − x_s) + k`` (``K`` is ``m × n``; ``k`` has ``m`` entries, default 0;
    ``x_s`` has ``n`` entries, default 0). Bad shapes → a :class:`~balustrade.errors.
    ShapeError` naming the argument."""

    K: np.ndarray
    k: np.ndarray | None = None
    x_s: np.ndarray | None = None

    def __post_init__(self) -> None:
        K = as_matrix(self.K, "AffinePolicy: K")
        m, n = K.shape
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "k", np.zeros(m) if self.k is None
                           else as_vector(self.k, "AffinePolicy: k", m))
        object.__setattr__(self, "x_s", np.zeros(n) if self.x_s is None
                           else as_vector(self.x_s, "AffinePolicy: x_s", n))

    @property
    def n(self) -> int:
        """The number of states."""
        return self.K.shape[1]

    @property
    def m(self) -> int:
        """The number of inputs."""
        return self.K.shape[0]

    def __call__(self, x: object) -> object:
        """``π(x)`` on numbers (a vector of ``m`` floats) or CasADi symbols (an ``m × 1``
        expression); a zero ``x_s`` or ``k`` adds no operation (the same rounding as
        ``K x``)."""
        if isinstance(x, (ca.SX, ca.MX, ca.DM)):
            d = ca.reshape(x, self.n, 1)
            if np.any(self.x_s):
                d = d - ca.DM(self.x_s)
            out = ca.mtimes(ca.DM(self.K), d)
            return out + ca.DM(self.k) if np.any(self.k) else out
        x = np.asarray(x, dtype=float).reshape(-1)
        d = x - self.x_s if np.any(self.x_s) else x
        out = self.K @ d
        return out + self.k if np.any(self.k) else out


#: the forms a terminal policy ``pi_f`` may take (:func:`as_policy`), for error messages
POLICY_FORMS = ("a matrix K (pi_f(x) = K x), a pair (K, k) (pi_f(x) = K x + k), an "
                "AffinePolicy(K, k, x_s), a casadi.Function of x, or a Python callable of x")


def as_policy(pi_f: object, nx: int, nu: int, where: str) -> object:
    """The terminal policy ``π_f`` of (5.17)/(6.14) in one form: a matrix ``K`` (``nu × nx``)
    becomes ``AffinePolicy(K)`` and a pair ``(K, k)`` ``AffinePolicy(K, k)`` (shapes checked,
    a :class:`~balustrade.errors.ShapeError` naming ``pi_f``), so Python and the emitted C
    evaluate the same expression; an :class:`AffinePolicy` is shape-checked against
    ``nx``/``nu``; any other callable (a ``casadi.Function``, a numpy law) is returned as
    is. Anything else (a tuple of another length, a scalar, ``None``) → a
    :class:`~balustrade.errors.BalustradeError` naming ``pi_f`` and :data:`POLICY_FORMS`,
    before any solve."""
    if isinstance(pi_f, tuple):
        if len(pi_f) != 2:
            raise BalustradeError(f"{where}: pi_f as a tuple must be the pair (K, k) of "
                                  f"pi_f(x) = K x + k, got {len(pi_f)} entries; accepted: "
                                  f"{POLICY_FORMS}")
        K = as_matrix(pi_f[0], f"{where}: pi_f K", (nu, nx))
        return AffinePolicy(K, as_vector(pi_f[1], f"{where}: pi_f k", nu))
    if isinstance(pi_f, (np.ndarray, list)):
        return AffinePolicy(as_matrix(pi_f, f"{where}: pi_f (the matrix K)", (nu, nx)))
    if isinstance(pi_f, AffinePolicy):
        as_matrix(pi_f.K, f"{where}: pi_f (AffinePolicy K)", (nu, nx))
        return pi_f
    if not callable(pi_f):
        raise BalustradeError(f"{where}: pi_f must be {POLICY_FORMS}; got "
                              f"{type(pi_f).__name__}")
    return pi_f


__all__ = ["POLICY_FORMS", "AffinePolicy", "as_policy"]
