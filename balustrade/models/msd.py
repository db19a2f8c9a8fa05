"""The mass–spring–damper chain of thesis Section 4.7 (SPEC §3.2), parametric in its springs.

``n`` unit masses, ``T_s = 0.2``, state ``(p₁..p_n, v₁..v_n)``::

    p⁺_i = p_i + T_s v_i
    v⁺_i = v_i − T_s c_{i−1,i}(p_i − p_{i−1}) − T_s d_{i−1,i}(v_i − v_{i−1})
               + T_s c_{i,i+1}(p_{i+1} − p_i) + T_s d_{i,i+1}(v_{i+1} − v_i) + u_i

with free chain ends (``c₀,₁ = d₀,₁ = c_{n,n+1} = d_{n,n+1} = 0``), internal dampers
``d = 0.1``, and ``u_i`` entering without ``T_s`` (as printed). The thesis prints "−" before
the last damper term (anti-damping); SPEC's [Default] "+" is used unless ``damper_sign=-1``.
The uncertain parameters are the ``n − 1`` springs ``θ_j = c_{j,j+1}`` (Assumption 4.1: the
dynamics are affine in θ), ``Θ₀ = [0.05, 0.25]^{n−1}``, ``|w| <= 10⁻³`` on all ``2n`` states,
``X = [−2.3, 2.3]^{2n}``, ``U = [−3.5, 3.5]^n``, ``x₀ = 0``, 150 steps.

The RL performance controller of the thesis is replaced by SPEC's deterministic aggressive
controller :func:`msd_performance`: ``u_{p,k} = sat(2(r_k − p₁) − v₁)`` on mass 1 with
``r_k = 2.5 sign(sin(2πk/50))``, deliberately outside ``X``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from balustrade._checks import as_count, as_scalar, as_vector
from balustrade.dsl.sets import Box
from balustrade.dsl.system_parametric import ParametricLinearSystem
from balustrade.errors import BalustradeError

TS = 0.2
DAMPING = 0.1
THETA_BOUNDS = (0.05, 0.25)
W_BOUND = 1e-3
X_BOUND = 2.3
U_BOUND = 3.5


def msd_chain(n: int = 3, Ts: float = TS, damping: float = DAMPING,
              damper_sign: int = 1, input_gain: float = 1.0) -> ParametricLinearSystem:
    """The chain of ``n >= 2`` masses as ``x⁺ = (A₀ + Σθ_jA_j)x + B₀u + w`` (4.6), with
    ``θ_j = c_{j,j+1}`` the spring between masses ``j`` and ``j + 1`` (``q = n − 1``).
    ``damper_sign`` is the sign before the last damper term (SPEC §3.2 [Typo?]);
    ``input_gain`` multiplies ``u_i`` in ``v⁺_i`` (``1`` as printed; ``Ts`` is the
    Euler-discretized force, a sensitivity variant of the reproduction)."""
    n = as_count(n, "msd_chain: n (number of masses)", low=2)
    Ts = as_scalar(Ts, "msd_chain: Ts", low=0.0, low_open=True)
    d = as_scalar(damping, "msd_chain: damping", low=0.0)
    if damper_sign not in (1, -1):
        raise BalustradeError(f"msd_chain: damper_sign must be +1 or -1, got {damper_sign!r}")
    P, V = slice(0, n), slice(n, 2 * n)
    A0 = np.eye(2 * n)
    A0[P, V] = Ts * np.eye(n)
    for i in range(n):  # v⁺_i rows: dampers to the left (−) and to the right (±)
        if i > 0:
            A0[n + i, n + i] -= Ts * d
            A0[n + i, n + i - 1] += Ts * d
        if i < n - 1:
            A0[n + i, n + i + 1] += damper_sign * Ts * d
            A0[n + i, n + i] -= damper_sign * Ts * d
    A_list = []
    for j in range(n - 1):  # spring c_{j,j+1} (0-based masses j and j + 1)
        Aj = np.zeros((2 * n, 2 * n))
        Aj[n + j, j + 1] += Ts      # + T_s c (p_{j+1} − p_j) on mass j
        Aj[n + j, j] -= Ts
        Aj[n + j + 1, j + 1] -= Ts  # − T_s c (p_{j+1} − p_j) on mass j + 1
        Aj[n + j + 1, j] += Ts
        A_list.append(Aj)
    gain = as_scalar(input_gain, "msd_chain: input_gain", low=0.0, low_open=True)
    B0 = np.vstack([np.zeros((n, n)), gain * np.eye(n)])
    return ParametricLinearSystem(A0, A_list, B0, None, name=f"msd{n}")


@dataclass(frozen=True)
class MSDSetup:
    """Sets and run settings of Section 4.7 (SPEC §3.2): ``Θ₀``, ``W``, ``X``, ``U``, the
    horizon ``N = 10`` ([Default]), ``steps = 150`` and ``x₀ = 0``."""

    n: int
    Theta0: Box
    W: Box
    X: Box
    U: Box
    N: int = 10
    steps: int = 150
    x0: np.ndarray = field(default=None)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        if self.x0 is None:
            object.__setattr__(self, "x0", np.zeros(2 * self.n))

    def constraint_volume(self) -> float:
        """``vol X = 4.6^{2n}`` (9474.3 for 3 masses, 4.019e10 for 8)."""
        return float(np.prod(self.X.ub - self.X.lb))

    def sample_theta(self, rng: np.random.Generator) -> np.ndarray:
        """``θ*`` uniform in ``Θ₀`` (the thesis draws it at random)."""
        return rng.uniform(self.Theta0.lb, self.Theta0.ub)


def msd_setup(n: int = 3, N: int = 10, steps: int = 150) -> MSDSetup:
    """``Θ₀ = [0.05, 0.25]^{n−1}``, ``W = [−10⁻³, 10⁻³]^{2n}``, ``X = [−2.3, 2.3]^{2n}``,
    ``U = [−3.5, 3.5]^n``."""
    n = as_count(n, "msd_setup: n (number of masses)", low=2)
    lo, hi = THETA_BOUNDS
    return MSDSetup(n=n, Theta0=Box(np.full(n - 1, lo), np.full(n - 1, hi), name="Theta0"),
                    W=Box.symmetric(W_BOUND, 2 * n, name="W"),
                    X=Box.symmetric(X_BOUND, 2 * n, name="X"),
                    U=Box.symmetric(U_BOUND, n, name="U"),
                    N=as_count(N, "msd_setup: N", low=1),
                    steps=as_count(steps, "msd_setup: steps", low=1))


def msd_reference(k: int, amplitude: float = 2.5, period: int = 50) -> float:
    """``r_k = 2.5 sign(sin(2πk/50))`` (SPEC §3.2 [Default]); outside ``X`` on purpose."""
    return float(amplitude * np.sign(np.sin(2.0 * np.pi * k / period)))


def msd_performance(k: int, x: object, n: int, u_bound: float = U_BOUND) -> np.ndarray:
    """The deterministic aggressive performance input ``u_{p,k}``: ``sat(2(r_k − p₁) − v₁)``
    on mass 1 (saturated to ``U``), zero on the other masses."""
    x = as_vector(x, "msd_performance: x", 2 * n)
    u = np.zeros(n)
    u[0] = np.clip(2.0 * (msd_reference(k) - x[0]) - x[n], -u_bound, u_bound)
    return u


__all__ = ["MSDSetup", "msd_chain", "msd_performance", "msd_reference", "msd_setup"]
