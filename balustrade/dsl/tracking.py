"""Reference-tracking stage costs (issue #13 §7; the regulation cost of (2.9) about a
reference instead of the origin).

``Σ_{i=0}^{N−1} ‖x_{i|k} − r_{i|k}‖²_Q + ‖u_{i|k} − u^ref_{i|k}‖²_R  +  ‖x_{N|k} − r_{N|k}‖²_P``

The references are parameters, given at solve time: a constant (shape ``(n, 1)``) or a
trajectory over the horizon (``(nx, N+1)`` for states, ``(nu, N)`` for inputs) with
``trajectory=True``::

    ocp.minimize(tracking_cost(ocp, Q, R, P=P))              # x_ref: a parameter (nx, 1)
    compiled.solve({"x0": x, "x_ref": [1.0, 0.0]})
    ocp.minimize(tracking_cost(ocp, Q, R, u_ref="u_ref", trajectory=True))
    compiled.solve({"x0": x, "x_ref": R_traj, "u_ref": U_traj})   # (nx, N+1), (nu, N)

A reference may also be a numeric constant or a CasADi expression of the OCP's symbols. The
cost is a convex quadratic in the decision variables, so both backends lower it.
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

Reference = str | ca.SX | np.ndarray | float | None


def reference(ocp: OCP, name: str, rows: int, cols: int) -> ca.SX:
    """A reference parameter of shape ``(rows, 1)`` (constant) or ``(rows, cols)``
    (trajectory); the existing parameter if ``name`` is declared with one of these shapes."""
    return ocp._shared_parameter(name, [(rows, cols), (rows, 1)], "reference")


def tracking_cost(ocp: OCP, Q: object | None = None, R: object | None = None,
                  P: object | None = None, x_ref: Reference = "x_ref",
                  u_ref: Reference = None, trajectory: bool = False,
                  label: str = "tracking") -> Cost:
    """``Σ_i ‖x_i − r_i‖²_Q + ‖u_i − u^ref_i‖²_R + ‖x_N − r_N‖²_P`` (each weight PSD, a
    scalar or a vector meaning a diagonal; a weight left ``None`` leaves its term out).

    ``x_ref``/``u_ref``: a parameter name (declared ``(n, 1)``, or ``(nx, N+1)``/``(nu, N)``
    with ``trajectory=True``), a number or array (a fixed reference), a CasADi expression,
    or ``None`` (zero: regulate to the origin).
    """
    sys = ocp._need_system("tracking_cost")
    if Q is None and R is None and P is None:
        raise BalustradeError(f"{ocp.name}: {label}: give at least one of Q, R, P")
    total = ca.SX(0)
    if Q is not None or P is not None:
        r = _resolve(ocp, x_ref, sys.nx, ocp.N + 1, trajectory, f"{label}: x_ref")
        weights = [None if W is None else ca.DM(weight_matrix(W, sys.nx, f"{ocp.name}: "
                                                              f"{label}: {which}"))
                   for W, which in ((Q, "Q"), (P, "P"))]
        for i in range(ocp.N + 1):
            Wm = weights[0] if i < ocp.N else weights[1]
            if Wm is not None:
                e = ocp.x[:, i] - _column(r, i)
                total = total + ca.mtimes([e.T, Wm, e])
    if R is not None:
        Rm = weight_matrix(R, sys.nu, f"{ocp.name}: {label}: R")
        v = _resolve(ocp, u_ref, sys.nu, ocp.N, trajectory, f"{label}: u_ref")
        for i in range(ocp.N):
            e = ocp.u[:, i] - _column(v, i)
            total = total + ca.mtimes([e.T, ca.DM(Rm), e])
    return Cost([Term(TermKind.SMOOTH, total, 1.0, label)])


def _column(ref: ca.SX, i: int) -> ca.SX:
    return ref[:, 0] if ref.shape[1] == 1 else ref[:, i]


def _resolve(ocp: OCP, ref: Reference, rows: int, cols: int, trajectory: bool,
             where: str) -> ca.SX:
    """A reference as an ``(rows, 1)`` or ``(rows, cols)`` expression."""
    if ref is None:
        return ca.SX.zeros(rows, 1)
    if isinstance(ref, str):
        return reference(ocp, ref, rows, cols if trajectory else 1)
    if isinstance(ref, (ca.SX, ca.DM)):
        expr = ca.SX(ref)
        if expr.shape[1] == rows and expr.shape[0] == 1 and rows > 1:
            expr = expr.T
        if expr.shape not in ((rows, 1), (rows, cols)):
            raise ShapeError(f"{ocp.name}: {where}", f"({rows}, 1) or ({rows}, {cols})",
                             expr.shape)
        return expr
    arr = as_float_array(ref, f"{ocp.name}: {where}")
    if not np.all(np.isfinite(arr)):
        raise NonFiniteError(f"{ocp.name}: {where}: contains NaN or inf")
    if arr.ndim == 0:
        arr = np.full((rows, 1), float(arr))
    elif arr.ndim == 1:
        arr = arr.reshape(-1, 1)
    if arr.shape not in ((rows, 1), (rows, cols)):
        raise ShapeError(f"{ocp.name}: {where}", f"({rows}, 1) or ({rows}, {cols})", arr.shape)
    return ca.SX(ca.DM(arr))
