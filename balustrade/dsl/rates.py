"""Input rates: rate limits and rate costs on ``Δu_{i|k} = u_{i|k} − u_{i−1|k}``.

Not in the thesis, but what a control engineer expects of an MPC (issue #13 §7). The first
increment is taken against the input applied at the previous sample, a parameter
``u_{−1|k} = u_prev`` (declared on first use, shared by every rate block of the problem)::

    du = input_rates(ocp)                      # (nu, N): u_0 − u_prev, u_1 − u_0, ...
    rate_limit(ocp, 0.5)                       # |Δu_i| <= 0.5 (hard)
    xi = rate_limit(ocp, 0.5, soft=True)       # |Δu_i| <= 0.5 + ξ_i, ξ_i >= 0 (named slack)
    ocp.minimize(... + rate_cost(ocp, R) + sum_norms(xi, 1))   # Σ_i ‖Δu_i‖²_R

A soft rate limit uses the slack machinery of :meth:`OCP.state_constraint` (SPEC §1.12):
one nonnegative slack per input and step, returned so that the caller prices it. Every
block is affine (hard) or affine in the slack (soft), and the cost is a convex quadratic, so
both backends lower them. A closed loop passes ``u_prev`` (the input it applied last), e.g.
:class:`balustrade.control.mpc.MPCController`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import casadi as ca
import numpy as np

from balustrade._checks import as_float_array
from balustrade.dsl.costs import Cost, Term, TermKind, weight_matrix
from balustrade.errors import BalustradeError, NonFiniteError, ShapeError

if TYPE_CHECKING:  # no import cycle: ocp.py imports this module lazily
    from balustrade.dsl.ocp import OCP

#: the default name of the previous-input parameter ``u_{−1|k}``
U_PREV = "u_prev"


def previous_input(ocp: OCP, name: str = U_PREV) -> ca.SX:
    """The parameter ``u_{−1|k}`` (the input applied at the previous sample), shape
    ``(nu, 1)``; declared on first use, the existing one afterwards."""
    sys = ocp._need_system("previous_input")
    return ocp._shared_parameter(name, [(sys.nu, 1)], "previous input")


def input_rates(ocp: OCP, u_prev: str | ca.SX = U_PREV) -> ca.SX:
    """``Δu = [u_0 − u_{−1}, u_1 − u_0, …, u_{N−1} − u_{N−2}]``, an ``(nu, N)`` expression;
    ``u_prev`` is a parameter name (declared if needed) or an expression of shape (nu, 1)."""
    sys = ocp._need_system("input_rates")
    if isinstance(u_prev, str):
        prev = previous_input(ocp, u_prev)
    else:
        prev = ocp._as_column(u_prev, sys.nu, "input_rates: u_prev")
    return ocp.u - ca.horzcat(prev, ocp.u[:, :-1])


def rate_limit(ocp: OCP, rate: object, soft: bool = False, u_prev: str | ca.SX = U_PREV,
               name: str = "rate") -> ca.SX | None:
    """``|Δu_{i|k}| <= r`` elementwise for ``i ∈ I[0, N−1]`` (``r`` a scalar or one bound
    per input, ``r >= 0``).

    ``soft=True`` makes it ``|Δu_{i|k}| <= r + ξ_{i|k}`` with a slack variable
    ``ξ >= 0`` of shape ``(nu, N)`` named ``xi_<name>``, which is returned (price it in the
    cost, e.g. ``sum_norms(xi, 1)``); the hard form returns ``None``.
    """
    sys = ocp._need_system("rate_limit")
    r = _rate_bound(rate, sys.nu, f"{ocp.name}: {name}: rate")
    du = input_rates(ocp, u_prev)
    bound = ca.repmat(ca.DM(r), 1, ocp.N)
    xi = ocp._slack("variable", (sys.nu, ocp.N), False, name) if soft else None
    slack = 0 if xi is None else ca.vertcat(xi, xi)
    ocp.le(ca.vertcat(du - bound, -du - bound), slack, name=name, tag="rate",
           rate=r.tolist(), soft=bool(soft))
    return xi


def rate_cost(ocp: OCP, R: object | None = None, u_prev: str | ca.SX = U_PREV,
              label: str = "rate_cost") -> Cost:
    """``Σ_{i=0}^{N−1} ‖Δu_{i|k}‖²_R`` with ``R ⪰ 0`` (``R = I`` by default; a scalar or a
    vector is a diagonal), a smooth convex cost term to add to the objective."""
    sys = ocp._need_system("rate_cost")
    Rm = weight_matrix(R, sys.nu, f"{ocp.name}: {label}: R")
    du = input_rates(ocp, u_prev)
    total = ca.SX(0)
    for i in range(ocp.N):
        total = total + ca.mtimes([du[:, i].T, ca.DM(Rm), du[:, i]])
    return Cost([Term(TermKind.SMOOTH, total, 1.0, label)])


def _rate_bound(rate: object, nu: int, where: str) -> np.ndarray:
    arr = as_float_array(rate, where)
    if arr.ndim == 0:
        arr = np.full(nu, float(arr))
    arr = arr.reshape(-1)
    if arr.size != nu:
        raise ShapeError(where, f"a scalar or ({nu},)", arr.shape)
    if not np.all(np.isfinite(arr)):
        raise NonFiniteError(f"{where}: contains NaN or inf (leave out a limit instead)")
    if np.any(arr < 0):
        raise BalustradeError(f"{where}: a rate limit must be >= 0, got {arr.tolist()}")
    return arr
