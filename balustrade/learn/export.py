"""Export a trained :class:`~balustrade.learn.train.MLPModel` to CasADi (float64).

The network becomes an SX expression of the state, so the approximate PCBF problems
(7.5)/(7.6) compile with it on the CasADi backend (and through CasADi's C code generation).
Softplus is written exactly as PyTorch evaluates it (``x`` above the threshold 20,
``log1p(exp(x))`` below, with ``if_else`` so neither branch overflows), so exported and
PyTorch networks agree to rounding (~1e-15). No PyTorch import here.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from balustrade.errors import ShapeError
from balustrade.learn.train import SOFTPLUS_THRESHOLD, MLPModel


def softplus(z: ca.SX) -> ca.SX:
    """``torch.nn.Softplus()`` (β = 1, threshold 20) on CasADi symbols."""
    return ca.if_else(z > SOFTPLUS_THRESHOLD, z, ca.log1p(ca.exp(z)))


def expression(model: MLPModel, x: ca.SX) -> ca.SX:
    """``ĥ(x)`` as a CasADi expression of ``x`` (an ``(nx, 1)`` symbol or expression)."""
    x = ca.SX(x) if not isinstance(x, (ca.SX, ca.MX)) else x
    if x.numel() != model.nx:
        raise ShapeError("export: network input", (model.nx, 1), x.shape)
    z = (ca.vec(x) - ca.DM(model.mean)) / ca.DM(model.scale)
    n = len(model.weights)
    for k, (W, b) in enumerate(zip(model.weights, model.biases)):
        z = ca.mtimes(ca.DM(W), z) + ca.DM(b)
        if k < n - 1:
            z = softplus(z)
    return z ** 3 if model.output_transform == "cbrt" else z


def to_casadi(model: MLPModel, name: str = "h_hat") -> ca.Function:
    """``ĥ`` as a CasADi Function ``x ↦ ĥ(x)`` (SX, float64); usable as ``h_hat`` in
    :mod:`balustrade.problems.approximate` and :mod:`balustrade.control.approximate`."""
    x = ca.SX.sym("x", model.nx)
    return ca.Function(name, [x], [expression(model, x)], ["x"], ["h"])


def evaluate(fn: ca.Function, X: np.ndarray) -> np.ndarray:
    """Evaluate an exported Function on the rows of ``X`` in one batched call."""
    X = np.atleast_2d(np.asarray(X, dtype=float))
    return np.asarray(fn.map(len(X))(X.T)).reshape(-1)
