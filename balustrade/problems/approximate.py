"""The horizon-free approximate PCBF problems (thesis Section 7.2, SPEC §2.28).

Given an explicit approximation ``ĥ`` of the PCBF ``h_PB`` (2.24) or of the extended
``h`` (7.7) — a trained network exported to CasADi, or any hand-written function:

* :func:`max_decrease_problem` — (7.6): ``Δĥ(x) = ĥ(x) − min_{u ∈ U} ĥ(f(x, u))``; the OCP
  minimizes ``ĥ(f(x, u))`` over ``u ∈ U`` (a nonconvex NLP in ``u`` only);
* :func:`approximate_filter_problem` — (7.5): ``min ‖u − u_p‖²`` s.t.
  ``ĥ(f(x, u)) − ĥ(x) <= −ρ Δĥ(x)`` and ``u ∈ U``, ``ρ ∈ (0, 1]``;
* :func:`decrease_bound` — the right side of (7.5).

The multi-start that solves (7.6) (:class:`~balustrade.control.decrease.MaximalDecrease`)
and Algorithm 7.5 (:class:`~balustrade.control.approximate.ApproximatePCBFFilter`) live
in :mod:`balustrade.control`: this module holds formulations only.

Neither problem depends on the prediction horizon ``N`` of (2.24): ``ĥ`` carries it.
By Proposition 7.3 the minimizer of (7.6) is feasible in (7.5) for every ``x`` and every
``ρ ∈ (0, 1]``; the filter is warm-started with it.
"""

from __future__ import annotations

from collections.abc import Callable

import casadi as ca
import numpy as np

from balustrade._checks import as_count, check_name, check_symbolic
from balustrade.dsl import OCP, Set, System, squared_norm
from balustrade.dsl.sets import Box
from balustrade.errors import BalustradeError, ShapeError, moved_names
from balustrade.problems._args import check_system_sets, nonnegative

HHat = ca.Function | Callable[[ca.SX], object]


def as_h_function(h_hat: HHat, nx: int, name: str = "h_hat") -> ca.Function:
    """Normalize ``ĥ`` (a CasADi Function ``x ↦ ĥ(x)`` or a callable on an ``(nx, 1)`` SX
    symbol) to a CasADi Function with one input of shape ``(nx, 1)`` and a scalar output."""
    check_name(name, "as_h_function: name")
    nx = as_count(nx, f"{name}: nx", low=1)
    if isinstance(h_hat, ca.Function):
        if h_hat.n_in() != 1 or h_hat.size1_in(0) * h_hat.size2_in(0) != nx:
            raise ShapeError(f"{name}: input of the CasADi Function", (nx, 1),
                             (h_hat.size1_in(0), h_hat.size2_in(0)))
        if h_hat.numel_out(0) != 1:
            raise ShapeError(f"{name}: output of the CasADi Function", "a scalar",
                             (h_hat.size1_out(0), h_hat.size2_out(0)))
        return h_hat
    if not callable(h_hat):
        raise BalustradeError(f"{name}: ĥ must be a CasADi Function or a callable on an "
                              f"({nx}, 1) symbol, got {type(h_hat).__name__}")
    x = ca.SX.sym("x", nx)
    try:
        value = ca.SX(h_hat(x))
    except Exception as exc:  # the user's function failed on a symbol
        raise BalustradeError(f"{name}: ĥ(x) failed on a symbol of shape ({nx}, 1): {exc}"
                              ) from exc
    if value.numel() != 1:
        raise ShapeError(f"{name}: ĥ(x)", "a scalar", value.shape)
    check_symbolic(value, f"{name}: ĥ(x)")
    return ca.Function(name, [x], [value], ["x"], ["h"])


def _input_variable(ocp: OCP, U: Set, nu: int) -> ca.SX:
    """``u ∈ U``: simple bounds for a box (cheapest for an NLP solver), rows ``c_U(u) <= 0``
    otherwise."""
    if U.dim != nu:
        raise ShapeError(f"{ocp.name}: input set {U.name}", f"dimension {nu}",
                         f"dimension {U.dim}")
    if isinstance(U, Box):
        return ocp.variable("u", nu, lb=U.lb, ub=U.ub, role="input")
    u = ocp.variable("u", nu, role="input")
    ocp.le(U.c(u), 0, name="input", tag="input")
    return u


def max_decrease_problem(system: System, U: Set, h_hat: HHat,
                         name: str = "approx_max_decrease") -> OCP:
    """(7.6) as ``min_{u ∈ U} ĥ(f(x0, u))``; ``Δĥ(x0) = ĥ(x0) − optimum``.

    Parameters: ``x0``. Variable: ``u``.
    """
    check_system_sets(name, system, U=U)
    h = as_h_function(h_hat, system.nx)
    ocp = OCP(None, name=name)
    u = _input_variable(ocp, U, system.nu)
    x0 = ocp.parameter("x0", system.nx)
    ocp.minimize(h(system(x0, u)))
    return ocp


def approximate_filter_problem(system: System, U: Set, h_hat: HHat, eps: float = 1e-6,
                               name: str = "approx_filter") -> OCP:
    """(7.5): ``min ‖u − u_p‖²`` s.t. ``ĥ(f(x0, u)) − ĥ(x0) <= −ρ Δĥ + eps`` and ``u ∈ U``
    (for ``Δĥ < 0`` the bound is extended as in :func:`decrease_bound`).

    Parameters: ``x0``, ``u_p``, ``dh`` (``Δĥ(x0)`` from (7.6)) and ``rho`` (``ρ ∈ (0, 1]``,
    default 1), so one compiled problem serves every ``ρ``. ``eps`` is the numerical margin
    that keeps the (7.6) minimizer strictly feasible at ``ρ = 1`` (Proposition 7.3).
    """
    check_system_sets(name, system, U=U)
    eps = nonnegative(eps, f"{name}: eps")
    h = as_h_function(h_hat, system.nx)
    ocp = OCP(None, name=name)
    u = _input_variable(ocp, U, system.nu)
    x0 = ocp.parameter("x0", system.nx)
    u_p = ocp.parameter("u_p", system.nu)
    dh = ocp.parameter("dh", 1)
    rho = ocp.parameter("rho", 1, value=1.0)
    ocp.decrease(h(system(x0, u)) - h(x0), decrease_bound(dh, rho) + eps,
                 name="approx_decrease")
    ocp.minimize(squared_norm(u - u_p, label="filter"))
    return ocp


def decrease_bound(dh: object, rho: object) -> object:
    """Right side of (7.5): ``max(−ρ Δĥ, −Δĥ)``, i.e. ``−ρ Δĥ`` when ``Δĥ >= 0`` (the
    thesis' bound) and ``−Δĥ`` when ``Δĥ < 0`` (works on numbers and CasADi symbols).

    [Gap] Proposition 7.3 uses ``−Δĥ <= −ρ Δĥ``, true only for ``Δĥ >= 0`` (a CBF outside
    ``S_PB``). A learned ``ĥ``, or the extended ``h`` inside ``S_PB``, can have ``Δĥ < 0``
    (no input decreases it); then ``−ρ Δĥ < −Δĥ`` and (7.5) would be infeasible for
    ``ρ < 1``. With the bound above the (7.6) minimizer is feasible for every ``x`` and
    ``ρ ∈ (0, 1]``, the bound is continuous in ``Δĥ``, and where ``ĥ`` cannot decrease the
    filter asks for the least increase (``ĥ(f(x, u)) <= min_v ĥ(f(x, v))``), which keeps
    the next state in ``{ĥ <= 0}`` whenever some input can.
    """
    fmax = ca.fmax if isinstance(dh, (ca.SX, ca.MX, ca.DM)) else np.maximum
    return fmax(-rho * dh, -dh)

#: names that moved out of this module (issue #13): deprecated aliases (errors.moved_names)
__getattr__ = moved_names(__name__, {
    "DecreaseResult": "balustrade.control.decrease",
    "MaximalDecrease": "balustrade.control.decrease",
    "coarse_grid": "balustrade.control.decrease",
    "in_set": "balustrade.control.decrease",
})
