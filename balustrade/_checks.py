"""Input validation shared by all layers: shapes, finiteness, positive semidefiniteness."""

from __future__ import annotations

import numpy as np

from balustrade.errors import NonFiniteError, NotPSDError, ShapeError


def as_matrix(value: object, block: str, shape: tuple[int | None, int | None] | None = None,
              finite: bool = True) -> np.ndarray:
    """Return ``value`` as a 2-D float array, checking its shape (``None`` = any size)."""
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        arr = arr.reshape(1, 1)
    elif arr.ndim == 1:
        arr = arr.reshape(-1, 1) if shape is None or shape[1] in (1, None) else arr.reshape(1, -1)
    if arr.ndim != 2:
        raise ShapeError(block, "a 2-D matrix", f"an array with shape {arr.shape}")
    if shape is not None:
        for want, got in zip(shape, arr.shape):
            if want is not None and want != got:
                raise ShapeError(block, _fmt(shape), arr.shape, what="shape")
    if finite and not np.all(np.isfinite(arr)):
        raise NonFiniteError(f"{block}: contains NaN or inf (shape {arr.shape})")
    return arr


def as_vector(value: object, block: str, size: int | None = None,
              finite: bool = True) -> np.ndarray:
    """Return ``value`` as a 1-D float array of length ``size`` (a column or row is flattened)."""
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 2 and 1 in arr.shape:
        arr = arr.reshape(-1)
    elif arr.ndim == 0:
        arr = arr.reshape(1)
    if arr.ndim != 1:
        raise ShapeError(block, f"a vector of length {size if size is not None else 'n'}",
                         f"an array with shape {arr.shape}")
    if size is not None and arr.size != size:
        raise ShapeError(block, (size,), arr.shape)
    if finite and not np.all(np.isfinite(arr)):
        raise NonFiniteError(f"{block}: contains NaN or inf: {arr}")
    return arr


def check_psd(M: np.ndarray, block: str, strict: bool = False, tol: float = 1e-9) -> np.ndarray:
    """Check that ``M`` is symmetric positive semidefinite (definite if ``strict``)."""
    M = as_matrix(M, block)
    if M.shape[0] != M.shape[1]:
        raise ShapeError(block, "a square matrix", M.shape)
    scale = max(1.0, float(np.max(np.abs(M))))
    if not np.allclose(M, M.T, atol=tol * scale):
        raise NotPSDError(f"{block}: matrix of shape {M.shape} is not symmetric")
    lam_min = float(np.min(np.linalg.eigvalsh(0.5 * (M + M.T))))
    if lam_min < -tol * scale or (strict and lam_min <= tol * scale):
        kind = "positive definite" if strict else "positive semidefinite"
        raise NotPSDError(f"{block}: matrix of shape {M.shape} is not {kind} "
                          f"(smallest eigenvalue {lam_min:.3g})")
    return 0.5 * (M + M.T)


def _fmt(shape: tuple[int | None, ...]) -> str:
    return "(" + ", ".join("n" if s is None else str(s) for s in shape) + ")"
