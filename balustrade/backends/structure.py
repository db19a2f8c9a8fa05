"""Structure detection: split CasADi expressions into the affine and convex-quadratic
pieces a conic (cvxpy) backend can hold.

The cvxpy lowering is a chain of small passes (DESIGN.md, "models to learn from"): each
block's rows are classified here, then :mod:`balustrade.backends.cvxpy_backend` turns the
pieces into DPP-parametrized cvxpy atoms. Parameters must enter affinely and must not
multiply decision variables inside a constraint; the multiplier of a parameter-affine
linear cost term is allowed (``(b + M p)ᵀ w`` is DPP).
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np
import scipy.sparse as sp

from balustrade.errors import ConvexityError


@dataclass
class Affine:
    """``A w + B p + c`` (sparse ``A``, ``B``)."""

    A: sp.csr_matrix
    B: sp.csr_matrix
    c: np.ndarray


@dataclass
class QuadraticRow:
    """``½ ‖Lw w_I + Lp p_J‖² + aᵀw + bᵀp + c``: a convex quadratic in ``(w, p)`` jointly.

    Written with a square-root factor so that the cvxpy atom ``sum_squares`` of a
    parameter-affine argument is DPP (e.g. ``h(Ax + Bu)`` with the state ``x`` a parameter).
    """

    w_index: np.ndarray
    p_index: np.ndarray
    Lw: np.ndarray
    Lp: np.ndarray
    a: sp.csr_matrix
    b: sp.csr_matrix
    c: float


@dataclass
class QuadraticCost:
    """``½ (w_I)ᵀ H (w_I) + (a + M p)ᵀ w + (terms in p only)``."""

    index: np.ndarray
    H: np.ndarray
    a: np.ndarray
    M: sp.csr_matrix


def _dm_to_sparse(m: ca.DM) -> sp.csr_matrix:
    m = ca.DM(m)
    if m.nnz() == 0:
        return sp.csr_matrix(m.shape)
    col, row = m.sparsity().get_ccs()
    return sp.csc_matrix((np.asarray(m.nonzeros(), dtype=float), row, col),
                         shape=m.shape).tocsr()


def _constant(expr: ca.SX, w: ca.SX, p: ca.SX) -> bool:
    return not (ca.depends_on(expr, w) or ca.depends_on(expr, p)) if expr.nnz() else True


def _evaluate(expr: ca.SX, w: ca.SX, p: ca.SX) -> ca.DM:
    f = ca.Function("f", [w, p], [expr])
    return f(np.zeros(w.numel()), np.zeros(p.numel()))


def affine(expr: ca.SX, w: ca.SX, p: ca.SX, block: str) -> Affine | None:
    """Return the affine decomposition of ``expr`` or ``None`` if it is not affine."""
    Jw = ca.jacobian(expr, w)
    Jp = ca.jacobian(expr, p) if p.numel() else ca.SX(expr.numel(), 0)
    if not (_constant(Jw, w, p) and _constant(Jp, w, p)):
        return None
    c = np.asarray(_evaluate(expr, w, p), dtype=float).reshape(-1)
    return Affine(_dm_to_sparse(_evaluate(Jw, w, p)), _dm_to_sparse(_evaluate(Jp, w, p)), c)


def quadratic_row(expr: ca.SX, w: ca.SX, p: ca.SX, block: str, row: int | None = None
                  ) -> QuadraticRow:
    """Decompose a scalar that is a convex quadratic of ``(w, p)`` jointly."""
    where = f"block {block!r}" + (f", row {row}" if row is not None else "")
    y = ca.vertcat(w, p)
    grad = ca.gradient(expr, y)
    H_sym = ca.jacobian(grad, y)
    if not _constant(H_sym, w, p):
        raise ConvexityError(
            f"{where}: the expression is neither affine nor a convex quadratic of the decision "
            "variables and parameters; the cvxpy backend cannot hold it (use backend='casadi')")
    H = np.asarray(ca.densify(_evaluate(H_sym, w, p)), dtype=float)
    index = np.flatnonzero(np.any(H != 0, axis=0))
    Hs = H[np.ix_(index, index)]
    _require_psd(Hs, where)
    L = psd_factor(Hs)
    nw = int(w.numel())
    in_w = index < nw
    g0 = np.asarray(_evaluate(grad, w, p), dtype=float).reshape(-1)
    return QuadraticRow(index[in_w], index[~in_w] - nw, L[:, in_w], L[:, ~in_w],
                        sp.csr_matrix(g0[:nw].reshape(1, -1)),
                        sp.csr_matrix(g0[nw:].reshape(1, -1)),
                        float(_evaluate(expr, w, p)))


def quadratic_cost(expr: ca.SX, w: ca.SX, p: ca.SX, label: str) -> QuadraticCost:
    """Decompose a smooth scalar cost term that is convex quadratic in ``w``."""
    grad_w = ca.gradient(expr, w)
    Hw = ca.jacobian(grad_w, w)
    M = ca.jacobian(grad_w, p) if p.numel() else ca.SX(w.numel(), 0)
    if not (_constant(Hw, w, p) and _constant(M, w, p)):
        raise ConvexityError(f"cost term {label!r}: not a quadratic function of the decision "
                             "variables (with a parameter-affine linear part); the cvxpy "
                             "backend cannot hold it (use backend='casadi')")
    H = np.asarray(ca.densify(_evaluate(Hw, w, p)), dtype=float)
    index = np.flatnonzero(np.any(H != 0, axis=0))
    Hs = H[np.ix_(index, index)]
    _require_psd(Hs, f"cost term {label!r}")
    a = np.asarray(_evaluate(grad_w, w, p), dtype=float).reshape(-1)
    return QuadraticCost(index, Hs, a, _dm_to_sparse(_evaluate(M, w, p)))


def _require_psd(H: np.ndarray, where: str) -> None:
    if H.size == 0:
        return
    lam = np.linalg.eigvalsh(0.5 * (H + H.T))
    if lam.min() < -1e-9 * max(1.0, float(np.abs(lam).max())):
        raise ConvexityError(f"{where}: the Hessian has a negative eigenvalue "
                             f"({lam.min():.3g}); a nonconvex block cannot be sent to cvxpy "
                             "(use backend='casadi')")


def psd_factor(H: np.ndarray) -> np.ndarray:
    """``L`` with ``LᵀL = H`` for ``H ⪰ 0`` (eigen-factor, drops null directions)."""
    lam, V = np.linalg.eigh(0.5 * (H + H.T))
    keep = lam > 1e-12 * max(1.0, float(lam.max(initial=0.0)))
    return (V[:, keep] * np.sqrt(lam[keep])).T
