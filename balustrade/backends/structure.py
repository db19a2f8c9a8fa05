"""Structure detection: split CasADi expressions into the affine and convex-quadratic
pieces a conic (cvxpy) backend can hold.

The cvxpy lowering is a chain of small passes (DESIGN.md, "models to learn from"): each
block's rows are classified here, then :mod:`balustrade.backends.cvxpy_backend` turns the
pieces into DPP-parametrized cvxpy atoms. Parameters must enter affinely and must not
multiply decision variables inside a constraint; the multiplier of a parameter-affine
linear cost term is allowed (``(b + M p)ᵀ w`` is DPP).

A row that is a convex quadratic jointly in ``(w, p)`` — the tube's initial constraint
``(x_k − z_0)ᵀ P (x_k − z_0) <= 1`` ((2.15), (5.15b)) with the state ``x_k`` a parameter —
is kept about its centre (:func:`joint_quadratic`): ``½‖L_w w + L_p p + l‖² + affine``.
Expanding it around zero instead (``‖L z_0‖² − 2 (P x_k)ᵀ z_0 + x_kᵀ P x_k <= 1``) makes
the solver cancel constants of size ``|x_k|²‖P‖`` (1.4·10⁵ on the rendezvous), which it
cannot do to its tolerances.
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
class Quadratic:
    """``½ ‖L w_I‖² + (a + M p)ᵀ w + φ(p)``: convex quadratic in ``w`` (``LᵀL = H ⪰ 0`` on
    the indices ``I``), with a parameter-affine linear coefficient (DPP: ``(M p)ᵀ w``) and
    a parameter-only part ``φ(p) = expr(0, p)``. ``φ`` is affine (``b p + c``) or, when it
    is not, a CasADi function evaluated before each solve and fed to cvxpy as a derived
    parameter (e.g. ``−h(x)`` in the CBF decrease (2.20) with the state ``x`` a parameter).
    """

    index: np.ndarray
    L: np.ndarray
    a: np.ndarray
    M: sp.csr_matrix
    b: sp.csr_matrix | None
    c: float
    phi: ca.Function | None


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


def quadratic(expr: ca.SX, w: ca.SX, p: ca.SX, where: str) -> Quadratic:
    """Decompose a scalar that is a convex quadratic of the decision variables ``w`` whose
    gradient is affine in the parameters ``p``; refuse anything else naming ``where``."""
    grad_w = ca.gradient(expr, w)
    Hw = ca.jacobian(grad_w, w)
    M = ca.jacobian(grad_w, p) if p.numel() else ca.SX(w.numel(), 0)
    if not (_constant(Hw, w, p) and _constant(M, w, p)):
        raise ConvexityError(
            f"{where}: the expression is neither affine nor a convex quadratic of the decision "
            "variables (with parameters entering the linear part affinely); the cvxpy "
            "backend cannot hold it (use backend='casadi')")
    H = np.asarray(ca.densify(_evaluate(Hw, w, p)), dtype=float)
    index = np.flatnonzero(np.any(H != 0, axis=0))
    Hs = H[np.ix_(index, index)]
    _require_psd(Hs, where)
    a = np.asarray(_evaluate(grad_w, w, p), dtype=float).reshape(-1)
    phi_expr = ca.substitute(expr, w, ca.DM.zeros(w.numel()))
    phi_aff = affine(phi_expr, w, p, where)
    if phi_aff is not None:
        b, c, phi = phi_aff.B, float(phi_aff.c[0]), None
    else:
        b, c, phi = None, 0.0, ca.Function("phi", [p], [phi_expr])
    return Quadratic(index, psd_factor(Hs), a, _dm_to_sparse(_evaluate(M, w, p)), b, c, phi)


@dataclass
class JointQuadratic:
    """``½ ‖L_w w_I + L_p p_J + l‖² + aᵀ w + bᵀ p + c``: a row that is a convex quadratic
    jointly in the decision variables and the parameters (constant joint Hessian
    ``[L_w L_p]ᵀ[L_w L_p] ⪰ 0`` on the indices ``I``, ``J``), written about its centre.
    ``a``, ``b`` hold only the gradient outside the range of the Hessian (often zero), so
    that ``c`` is the row's value at the centre (``−1`` for an ellipsoid ``(x−z)ᵀP(x−z) − 1``).
    """

    w_index: np.ndarray
    p_index: np.ndarray
    Lw: np.ndarray
    Lp: np.ndarray
    l: np.ndarray
    a: np.ndarray
    b: np.ndarray
    c: float

    @property
    def linear_free(self) -> bool:
        """No affine part: the row is ``½‖·‖² + c <= 0``, i.e. the cone ``‖·‖ <= √(−2c)``."""
        return not (np.any(self.a) or np.any(self.b))


def joint_quadratic(expr: ca.SX, w: ca.SX, p: ca.SX) -> JointQuadratic | None:
    """Decompose a scalar row that is quadratic jointly in ``(w, p)`` with a positive
    semidefinite joint Hessian ``H`` as ``½‖L z + l‖² + gᵣᵀ z + c'`` (``z = (w, p)``,
    ``LᵀL = H``, ``Lᵀl`` the part of the gradient at zero ``g`` in the range of ``H``,
    ``gᵣ = g − Lᵀl``, ``c' = expr(0) − ½‖l‖²``); ``None`` if it is not (its Hessian depends on
    ``(w, p)``, e.g. a nonlinear ``−h(x_k)``, or is indefinite, e.g. ``−x_kᵀ P x_k``)."""
    z = ca.vertcat(w, p)
    grad = ca.gradient(expr, z)
    Hz = ca.jacobian(grad, z)
    if not _constant(Hz, w, p):
        return None
    H = np.asarray(ca.densify(_evaluate(Hz, w, p)), dtype=float)
    H = 0.5 * (H + H.T)
    support = np.flatnonzero(np.any(H != 0, axis=0))
    Hs = H[np.ix_(support, support)]
    if _negative_eigenvalue(Hs) is not None:
        return None
    L = psd_factor(Hs)
    g = np.asarray(_evaluate(grad, w, p), dtype=float).reshape(-1)
    c = float(np.asarray(_evaluate(expr, w, p), dtype=float).reshape(-1)[0])
    # L has orthogonal rows (eigen-factor): Lᵀl = projection of g onto range(H)
    row_norms2 = np.einsum("ij,ij->i", L, L)
    l = (L @ g[support]) / row_norms2 if L.size else np.zeros(0)
    g_rest = g.copy()
    g_rest[support] -= L.T @ l
    g_rest[np.abs(g_rest) <= 1e-12 * max(1.0, float(np.abs(g).max(initial=0.0)))] = 0.0
    nw = int(w.numel())
    in_w = support < nw
    return JointQuadratic(support[in_w], support[~in_w] - nw, L[:, in_w], L[:, ~in_w], l,
                          g_rest[:nw], g_rest[nw:], c - 0.5 * float(l @ l))


def _negative_eigenvalue(H: np.ndarray) -> float | None:
    """The smallest eigenvalue of ``H`` if it is negative beyond rounding (``H`` is not
    positive semidefinite), else ``None``."""
    if H.size == 0:
        return None
    lam = np.linalg.eigvalsh(0.5 * (H + H.T))
    return float(lam.min()) if lam.min() < -1e-9 * max(1.0, float(np.abs(lam).max())) \
        else None


def _require_psd(H: np.ndarray, where: str) -> None:
    lam_min = _negative_eigenvalue(H)
    if lam_min is not None:
        raise ConvexityError(f"{where}: the Hessian has a negative eigenvalue "
                             f"({lam_min:.3g}); a nonconvex block cannot be sent to cvxpy "
                             "(use backend='casadi')")


def psd_factor(H: np.ndarray) -> np.ndarray:
    """``L`` with ``LᵀL = H`` for ``H ⪰ 0`` and orthogonal rows; drops null directions.

    A diagonal ``H`` is factored exactly (``√H_ii``); otherwise by eigenvalues, dropping only
    those at the level of the eigen-solver's rounding (``8 n ε max λ``): a cost
    ``10¹² u₀² + u₁²`` must keep its ``u₁²``.
    """
    H = 0.5 * (H + H.T)
    n = H.shape[0]
    if n and not np.any(H - np.diag(np.diagonal(H))):
        d = np.diagonal(H)
        keep = np.flatnonzero(d > 0)
        L = np.zeros((keep.size, n))
        L[np.arange(keep.size), keep] = np.sqrt(d[keep])
        return L
    lam, V = np.linalg.eigh(H)
    keep = lam > 8 * max(n, 1) * np.finfo(float).eps * max(float(lam.max(initial=0.0)), 1e-300)
    return (V[:, keep] * np.sqrt(lam[keep])).T
