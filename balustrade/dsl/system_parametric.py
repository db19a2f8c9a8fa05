"""Linear dynamics affine in an uncertain parameter (Assumption 4.1, model (4.6), SPEC §2.19).

``x⁺ = A(θ) x + B(θ) u + E w`` with ``A(θ) = A₀ + Σ_j θ_j A_j`` and ``B(θ) = B₀ + Σ_j θ_j B_j``,
``θ ∈ R^q``. The regressor ``D(x, u) = [A₁x + B₁u, …, A_qx + B_qu]`` (SPEC §2.19) makes the
successor affine in θ, ``x⁺ = A₀x + B₀u + D(x, u) θ + E w``: the non-falsified set (4.7)
and the homothetic-tube constants of SPEC §2.20 are built from it.

:meth:`ParametricLinearSystem.nominal` is the :class:`~balustrade.dsl.system.LinearSystem`
at one θ (the plant at θ* in a simulation, or the nominal model at a centre);
:meth:`ParametricLinearSystem.as_system` is a :class:`~balustrade.dsl.system.System` with θ
as its parameter argument, for the horizon builder.
"""

from __future__ import annotations

from collections.abc import Sequence

import casadi as ca
import numpy as np

from balustrade._checks import as_matrix, as_vector, check_name
from balustrade.dsl.system import LinearSystem, System
from balustrade.errors import BalustradeError, ShapeError


class ParametricLinearSystem:
    """``x⁺ = (A₀ + Σθ_jA_j) x + (B₀ + Σθ_jB_j) u + E w`` (4.6).

    ``A_list`` and ``B_list`` hold the ``q`` matrices ``A_j (n, n)`` and ``B_j (n, m)``;
    either may be ``None`` (all zero) but not both, and given both they must have the same
    length. ``E`` defaults to ``I`` (``w`` enters every state additively, as in (4.6)).
    """

    def __init__(self, A0: object, A_list: Sequence[object] | None, B0: object,
                 B_list: Sequence[object] | None, E: object | None = None,
                 name: str = "parametric"):
        self.name = check_name(name, "ParametricLinearSystem: name")
        A0 = as_matrix(A0, f"{name}: A0")
        if A0.shape[0] != A0.shape[1]:
            raise ShapeError(f"{name}: A0", "a square matrix (n, n)", A0.shape)
        n = A0.shape[0]
        B0 = as_matrix(B0, f"{name}: B0", (n, None))
        m = B0.shape[1]
        if A_list is None and B_list is None:
            raise BalustradeError(f"{name}: A_list and B_list are both None: a parametric "
                                  "system needs at least one parameter (use LinearSystem)")
        A_seq = _matrices(A_list, f"{name}: A_list", (n, n))
        B_seq = _matrices(B_list, f"{name}: B_list", (n, m))
        if A_list is None:
            A_seq = tuple(np.zeros((n, n)) for _ in B_seq)
        if B_list is None:
            B_seq = tuple(np.zeros((n, m)) for _ in A_seq)
        if len(A_seq) != len(B_seq):
            raise ShapeError(f"{name}: B_list", f"{len(A_seq)} matrices (one per A_j, q)",
                             f"{len(B_seq)} matrices", what="")
        if not A_seq:
            raise ShapeError(f"{name}: A_list", "at least one matrix (q >= 1)", "none",
                             what="")
        E = np.eye(n) if E is None else as_matrix(E, f"{name}: E", (n, None))
        self.A0, self.B0, self.E = A0, B0, E
        self.A_list: tuple[np.ndarray, ...] = A_seq
        self.B_list: tuple[np.ndarray, ...] = B_seq
        self.nx, self.nu, self.nw, self.q = n, m, E.shape[1], len(A_seq)
        # stacked for vectorised evaluation: (q, n, n) and (q, n, m)
        self._A = np.stack(A_seq)
        self._B = np.stack(B_seq)

    def __repr__(self) -> str:
        return (f"ParametricLinearSystem(nx={self.nx}, nu={self.nu}, q={self.q}, "
                f"name={self.name!r})")

    # -- the model ---------------------------------------------------------------------
    def _theta(self, theta: object, block: str) -> np.ndarray:
        return as_vector(theta, f"{self.name}.{block}: theta", self.q)

    def A(self, theta: object) -> np.ndarray:
        """``A(θ) = A₀ + Σ_j θ_j A_j`` (4.6)."""
        th = self._theta(theta, "A")
        return self.A0 + np.tensordot(th, self._A, axes=1)

    def B(self, theta: object) -> np.ndarray:
        """``B(θ) = B₀ + Σ_j θ_j B_j`` (4.6)."""
        th = self._theta(theta, "B")
        return self.B0 + np.tensordot(th, self._B, axes=1)

    def D(self, x: object, u: object) -> np.ndarray:
        """``D(x, u) = [A₁x + B₁u, …, A_qx + B_qu]``, shape ``(n, q)`` (SPEC §2.19)."""
        x = as_vector(x, f"{self.name}.D: x", self.nx)
        u = as_vector(u, f"{self.name}.D: u", self.nu)
        return (self._A @ x + self._B @ u).T

    def affine_part(self, x: object, u: object) -> np.ndarray:
        """``A₀x + B₀u``: the successor without θ and w (``x⁺ = this + D(x, u)θ + Ew``)."""
        x = as_vector(x, f"{self.name}.affine_part: x", self.nx)
        u = as_vector(u, f"{self.name}.affine_part: u", self.nu)
        return self.A0 @ x + self.B0 @ u

    def step(self, x: object, u: object, theta: object, w: object | None = None) -> np.ndarray:
        """``x⁺ = A(θ)x + B(θ)u + Ew`` on numbers (``w = None``: no disturbance)."""
        x = as_vector(x, f"{self.name}.step: x", self.nx)
        u = as_vector(u, f"{self.name}.step: u", self.nu)
        th = self._theta(theta, "step")
        out = self.A(th) @ x + self.B(th) @ u
        if w is not None:
            out = out + self.E @ as_vector(w, f"{self.name}.step: w", self.nw)
        return out

    def nominal(self, theta: object) -> LinearSystem:
        """The :class:`~balustrade.dsl.system.LinearSystem` ``(A(θ), B(θ), E)`` at one θ."""
        th = self._theta(theta, "nominal")
        return LinearSystem(self.A(th), self.B(th), self.E, name=f"{self.name}_nominal")

    def as_system(self) -> System:
        """A :class:`~balustrade.dsl.system.System` ``f(x, u, w, θ)`` with ``ntheta = q``."""
        A0, B0, E = ca.DM(self.A0), ca.DM(self.B0), ca.DM(self.E)
        As = [ca.DM(a) for a in self.A_list]
        Bs = [ca.DM(b) for b in self.B_list]

        def f(x: ca.SX, u: ca.SX, w: ca.SX, th: ca.SX) -> ca.SX:
            out = ca.mtimes(A0, x) + ca.mtimes(B0, u) + ca.mtimes(E, w)
            for j in range(len(As)):
                out = out + th[j] * (ca.mtimes(As[j], x) + ca.mtimes(Bs[j], u))
            return out

        return System(f, self.nx, self.nu, self.nw, self.q, name=self.name)


def _matrices(mats: Sequence[object] | None, block: str,
              shape: tuple[int, int]) -> tuple[np.ndarray, ...]:
    if mats is None:
        return ()
    if isinstance(mats, np.ndarray) and mats.ndim == 3:
        mats = list(mats)
    if isinstance(mats, (str, bytes)) or not isinstance(mats, (list, tuple)):
        raise BalustradeError(f"{block}: expected a list of q matrices of shape {shape}, got "
                              f"{type(mats).__name__}")
    return tuple(as_matrix(M, f"{block}[{j}]", shape) for j, M in enumerate(mats))


__all__ = ["ParametricLinearSystem"]
