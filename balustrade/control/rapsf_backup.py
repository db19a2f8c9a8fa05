"""The backup policy ``π_Cf`` of Algorithm 4.1 (thesis Chapter 4, SPEC §2.21): what
:class:`~balustrade.control.rapsf.RAPSF` applies when no solve of (4.5) and no stored plan is
usable (``k_inf > N − 1``), after the estimator falsified every model, and on a non-finite
state (its NaN/inf entries read as 0).

The ``backup`` argument of ``RAPSF`` takes

* ``None`` — the default ``π_Cf(x) = K x``, safe on the §4.7 terminal set ``z = 0, α <= 1``
  (i.e. on ``𝕏₀``);
* an affine law ``(K_b, k_b)`` (or :class:`AffineBackup`): ``π_Cf(x) = K_b x + k_b``;
* a ``casadi.Function`` of ``x`` (or :class:`FunctionBackup`): one input with ``n`` entries,
  one output with ``m`` entries, no free symbols;
* any Python callable ``backup(x, u_p, k)``.

The first three are emitted into the C step by :func:`~balustrade.codegen.emit_rapsf`
(the function through CasADi's code generator, expanded to scalar operations); a Python
callable runs in Python only. Which safety a user's law gives is the user's to show
(Assumption 4.11 holds for the default on ``𝕏₀``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from balustrade._checks import as_matrix, as_vector
from balustrade.errors import BalustradeError, ShapeError

Backup = Callable[[np.ndarray, np.ndarray, int], np.ndarray]


@dataclass(frozen=True)
class AffineBackup:
    """``π_Cf(x) = K_b x + k_b`` (``K_b`` is ``m × n``, ``k_b`` has ``m`` entries)."""

    K_b: np.ndarray
    k_b: np.ndarray

    def __call__(self, x: np.ndarray, u_p: np.ndarray, k: int) -> np.ndarray:
        return self.K_b @ np.asarray(x, dtype=float).ravel() + self.k_b


@dataclass(frozen=True)
class FunctionBackup:
    """``π_Cf(x) = fn(x)`` for a ``casadi.Function`` ``fn`` (one input: ``x``, one output:
    ``u``)."""

    fn: ca.Function = field(repr=False)
    m: int

    def __call__(self, x: np.ndarray, u_p: np.ndarray, k: int) -> np.ndarray:
        out = self.fn(np.asarray(x, dtype=float).ravel())
        return np.asarray(ca.DM(out), dtype=float).reshape(self.m)

    def emittable(self, where: str) -> ca.Function:
        """The function expanded to scalar operations (self-contained C, no solver or
        library): a :class:`BalustradeError` naming ``backup`` when it cannot be expanded
        (e.g. it calls a solver or a Python callback)."""
        try:
            return self.fn.expand() if self.fn.is_a("MXFunction") else self.fn
        except RuntimeError as exc:
            raise BalustradeError(f"{where}: backup (casadi.Function {self.fn.name()!r}) "
                                  f"cannot be expanded to scalar operations for C: "
                                  f"{str(exc).splitlines()[-1][:200]}") from exc


def backup_policy(backup: object, n: int, m: int, K: np.ndarray, where: str
                  ) -> tuple[Backup, AffineBackup | FunctionBackup | None]:
    """``(callable backup(x, u_p, k), emittable law)`` of a ``backup`` argument (module
    docstring): the law is ``None`` for the default ``K x`` (the C's own) and for a Python
    callable (not emittable). Bad input → :class:`BalustradeError` naming ``backup``."""
    if backup is None:
        return (lambda x, u_p, k: K @ x), None
    if isinstance(backup, tuple):
        if len(backup) != 2:
            raise BalustradeError(f"{where}: backup as an affine law is a pair (K_b, k_b), "
                                  f"got a tuple of {len(backup)}")
        backup = AffineBackup(*backup)
    if isinstance(backup, AffineBackup):
        law = AffineBackup(as_matrix(backup.K_b, f"{where}: backup K_b", (m, n)),
                           as_vector(backup.k_b, f"{where}: backup k_b", m))
        return law, law
    if isinstance(backup, ca.Function):
        backup = FunctionBackup(backup, m)
    if isinstance(backup, FunctionBackup):
        law = _checked_function(backup.fn, n, m, where)
        return law, law
    if not callable(backup):
        raise BalustradeError(f"{where}: backup must be None (K x), an affine law (K_b, k_b), "
                              f"a casadi.Function of x or a callable backup(x, u_p, k); got "
                              f"{type(backup).__name__}")
    return backup, None


def _checked_function(fn: ca.Function, n: int, m: int, where: str) -> FunctionBackup:
    label = f"{where}: backup (casadi.Function {fn.name()!r})"
    if fn.n_in() != 1 or fn.n_out() != 1:
        raise BalustradeError(f"{label}: must have one input (x) and one output (u), has "
                              f"{fn.n_in()} inputs and {fn.n_out()} outputs")
    if fn.numel_in(0) != n or 1 not in fn.size_in(0):
        raise ShapeError(f"{label} input x", f"({n}, 1)", fn.size_in(0))
    if fn.numel_out(0) != m or 1 not in fn.size_out(0):
        raise ShapeError(f"{label} output u", f"({m}, 1)", fn.size_out(0))
    if fn.has_free():
        raise BalustradeError(f"{label}: has free symbols {fn.get_free()}; make them "
                              "constants (the backup is a function of x only)")
    return FunctionBackup(fn, m)


__all__ = ["AffineBackup", "Backup", "FunctionBackup", "backup_policy"]
