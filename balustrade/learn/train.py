"""Fitting ``ĥ`` (Section 7.2): a PyTorch (CPU) MLP with softplus activations.

Configurable widths/depth, optional cube-root output transform (Section 8.3: the network
fits ``∛h`` and ``ĥ = (net)³``, which compresses the large values of ``h_PB`` outside
``S_PB``), MSE or Huber loss, train/validation split, fixed seed. Inputs are standardized
with the training-set mean and standard deviation; the affine scaling is part of the model
and of its CasADi export (:mod:`balustrade.learn.export`).

The trained model is a :class:`MLPModel` — plain numpy weights — so exporting and using
it needs no PyTorch; only :func:`train` imports ``torch`` (the ``learn`` extra).
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np

from balustrade.errors import BalustradeError

SOFTPLUS_THRESHOLD = 20.0  # torch.nn.Softplus: linear above this input (beta = 1)


@dataclass
class TrainConfig:
    """Hyperparameters (defaults: the closed-loop network of Section 7.5 except epochs)."""

    widths: tuple[int, ...] = (16, 16, 16)
    epochs: int = 30
    lr: float = 5e-3
    batch_size: int = 8
    loss: str = "mse"            # "mse" | "huber"
    huber_delta: float = 1.0
    output_transform: str | None = None  # None | "cbrt"
    lr_schedule: str | None = None  # None (constant) | "cosine" (to 0 over all steps)
    val_fraction: float = 0.1
    seed: int = 0
    standardize: bool = True
    threads: int = 1

    def __post_init__(self) -> None:
        self.widths = tuple(int(w) for w in self.widths)
        if not self.widths or min(self.widths) < 1:
            raise BalustradeError(f"TrainConfig: widths must be positive, got {self.widths}")
        if self.loss not in ("mse", "huber"):
            raise BalustradeError(f"TrainConfig: loss must be 'mse' or 'huber', got {self.loss!r}")
        if self.output_transform not in (None, "cbrt"):
            raise BalustradeError("TrainConfig: output_transform must be None or 'cbrt', got "
                                  f"{self.output_transform!r}")
        if self.lr_schedule not in (None, "cosine"):
            raise BalustradeError("TrainConfig: lr_schedule must be None or 'cosine', got "
                                  f"{self.lr_schedule!r}")
        if not 0.0 <= self.val_fraction < 1.0:
            raise BalustradeError(f"TrainConfig: val_fraction must be in [0, 1), got "
                                  f"{self.val_fraction}")


@dataclass
class MLPModel:
    """``ĥ(x) = T(W_L σ(… σ(W_1 (x − μ)/s + b_1) …) + b_L)`` with ``σ`` = softplus and
    ``T`` the identity or ``y ↦ y³`` (cube-root training target)."""

    weights: list[np.ndarray]
    biases: list[np.ndarray]
    mean: np.ndarray
    scale: np.ndarray
    output_transform: str | None = None
    history: dict[str, list[float]] = field(default_factory=dict)
    config: dict = field(default_factory=dict)
    #: the softplus threshold of the hidden layers (:data:`SOFTPLUS_THRESHOLD`); the
    #: emitted C reads it from here (``<name>_NET_THRESHOLD``, codegen cannot import learn)
    softplus_threshold: ClassVar[float] = SOFTPLUS_THRESHOLD

    @property
    def nx(self) -> int:
        return int(self.weights[0].shape[1])

    def __call__(self, X: np.ndarray) -> np.ndarray:
        """Evaluate on rows of ``X`` (numpy, float64); mirrors the PyTorch forward pass."""
        z = (np.atleast_2d(np.asarray(X, dtype=float)) - self.mean) / self.scale
        for k, (W, b) in enumerate(zip(self.weights, self.biases)):
            z = z @ W.T + b
            if k < len(self.weights) - 1:
                z = np.where(z > SOFTPLUS_THRESHOLD, z,
                             np.log1p(np.exp(np.minimum(z, SOFTPLUS_THRESHOLD))))
        y = z[:, 0]
        return y ** 3 if self.output_transform == "cbrt" else y

    def save(self, path: str | Path) -> None:
        """``.npz`` with weights, scaling and a JSON header (config, history)."""
        arrays = {f"W{k}": W for k, W in enumerate(self.weights)}
        arrays.update({f"b{k}": b for k, b in enumerate(self.biases)})
        header = {"output_transform": self.output_transform, "history": self.history,
                  "config": self.config, "layers": len(self.weights)}
        np.savez(path, mean=self.mean, scale=self.scale, header=json.dumps(header), **arrays)

    @classmethod
    def load(cls, path: str | Path) -> MLPModel:
        with np.load(path, allow_pickle=False) as data:
            header = json.loads(str(data["header"]))
            n = header["layers"]
            return cls([data[f"W{k}"] for k in range(n)], [data[f"b{k}"] for k in range(n)],
                       data["mean"], data["scale"], header["output_transform"],
                       header.get("history", {}), header.get("config", {}))


def build_network(nx: int, widths: tuple[int, ...]):  # -> torch.nn.Sequential
    """The PyTorch MLP ``nx → widths… → 1`` with softplus activations (float64)."""
    import torch

    layers: list = []
    prev = nx
    for w in widths:
        layers += [torch.nn.Linear(prev, w), torch.nn.Softplus()]
        prev = w
    layers.append(torch.nn.Linear(prev, 1))
    return torch.nn.Sequential(*layers).double()


def to_model(net, mean: np.ndarray, scale: np.ndarray, output_transform: str | None,
             history: dict | None = None, config: dict | None = None) -> MLPModel:
    """Copy the weights of a PyTorch MLP built by :func:`build_network` to numpy."""
    import torch

    linear = [m for m in net if isinstance(m, torch.nn.Linear)]
    return MLPModel([m.weight.detach().double().numpy().copy() for m in linear],
                    [m.bias.detach().double().numpy().copy() for m in linear],
                    np.asarray(mean, float), np.asarray(scale, float), output_transform,
                    history or {}, config or {})


def train(X: np.ndarray, y: np.ndarray, config: TrainConfig | None = None,
          verbose: bool = False, return_net: bool = False,
          validation: tuple[np.ndarray, np.ndarray] | None = None):
    """Fit ``ĥ`` to ``(X, y)``; returns the :class:`MLPModel` (and the torch network if
    ``return_net``). ``history`` holds per-epoch training and validation loss (in the
    transformed output space), the validation MSE of ``ĥ`` itself and the learning rate
    at the end of each epoch (``lr_schedule="cosine"``: cosine annealing to 0 over all
    optimizer steps, so the last epochs average out the minibatch noise of small batches).

    ``validation=(X_val, y_val)``: an independent validation set (Section 8.3 samples it
    with its own seeds and goals) used for the history instead of a random split of
    ``(X, y)``; ``val_fraction`` is then ignored (all of ``(X, y)`` is trained on). Use it
    when ``(X, y)`` holds augmented copies of the same state (a random split would put
    copies on both sides)."""
    try:
        import torch
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise BalustradeError("training needs PyTorch: pip install 'balustrade[learn]' "
                              "(CPU wheel: pip install torch --index-url "
                              "https://download.pytorch.org/whl/cpu)") from exc
    cfg = config or TrainConfig()
    X = np.asarray(X, dtype=float)
    y = np.asarray(y, dtype=float).reshape(-1)
    if X.ndim != 2 or len(X) != len(y) or len(y) < 2:
        raise BalustradeError(f"train: need X of shape (n, nx) and y of shape (n,), got "
                              f"{X.shape} and {y.shape}")
    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(y))):
        raise BalustradeError("train: X and y must be finite")
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    rng = np.random.default_rng(cfg.seed)
    perm = rng.permutation(len(y))
    n_val = 0 if validation is not None else int(round(cfg.val_fraction * len(y)))
    val, tr = perm[:n_val], perm[n_val:]
    if validation is not None:
        Xv = np.asarray(validation[0], dtype=float)
        yv = np.asarray(validation[1], dtype=float).reshape(-1)
        if Xv.ndim != 2 or Xv.shape[1] != X.shape[1] or len(Xv) != len(yv) or not len(yv):
            raise BalustradeError(f"train: validation needs X_val of shape (m, {X.shape[1]}) "
                                  f"and y_val of shape (m,), got {Xv.shape} and {yv.shape}")
        if not (np.all(np.isfinite(Xv)) and np.all(np.isfinite(yv))):
            raise BalustradeError("train: X_val and y_val must be finite")
    mean = X[tr].mean(axis=0) if cfg.standardize else np.zeros(X.shape[1])
    scale = X[tr].std(axis=0) if cfg.standardize else np.ones(X.shape[1])
    scale = np.where(scale > 0, scale, 1.0)
    target = np.cbrt(y) if cfg.output_transform == "cbrt" else y
    Xt = torch.from_numpy((X - mean) / scale)
    yt = torch.from_numpy(target).reshape(-1, 1)
    if validation is not None:  # evaluated as rows appended after the training rows
        n_val = len(yv)
        val = np.arange(len(y), len(y) + n_val)
        Xt = torch.cat([Xt, torch.from_numpy((Xv - mean) / scale)])
        yt = torch.cat([yt, torch.from_numpy(np.cbrt(yv) if cfg.output_transform == "cbrt"
                                             else yv).reshape(-1, 1)])
        y = np.concatenate([y, yv])
    net = build_network(X.shape[1], cfg.widths)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    n_batches = -(-len(tr) // cfg.batch_size)
    sched = (torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=cfg.epochs * n_batches)
             if cfg.lr_schedule == "cosine" else None)
    loss_fn = (torch.nn.MSELoss() if cfg.loss == "mse"
               else torch.nn.HuberLoss(delta=cfg.huber_delta))
    gen = torch.Generator().manual_seed(cfg.seed)
    tr_idx = torch.from_numpy(tr)
    history: dict[str, list[float]] = {"train_loss": [], "val_loss": [], "val_mse_h": [],
                                       "lr": []}
    start = time.perf_counter()
    for epoch in range(cfg.epochs):
        net.train()
        order = tr_idx[torch.randperm(len(tr_idx), generator=gen)]
        total = 0.0
        for b in range(0, len(order), cfg.batch_size):
            idx = order[b:b + cfg.batch_size]
            opt.zero_grad()
            loss = loss_fn(net(Xt[idx]), yt[idx])
            loss.backward()
            opt.step()
            if sched is not None:
                sched.step()
            total += float(loss.detach()) * len(idx)
        history["train_loss"].append(total / max(len(tr), 1))
        history["lr"].append(float(opt.param_groups[0]["lr"]))  # at the end of the epoch
        if n_val:
            with torch.no_grad():
                pred = net(Xt[val])
                history["val_loss"].append(float(loss_fn(pred, yt[val])))
                h_pred = pred.numpy().reshape(-1)
                h_pred = h_pred ** 3 if cfg.output_transform == "cbrt" else h_pred
                history["val_mse_h"].append(float(np.mean((h_pred - y[val]) ** 2)))
        if verbose:
            print(f"epoch {epoch + 1}/{cfg.epochs}: train {history['train_loss'][-1]:.4g}"
                  + (f", val {history['val_loss'][-1]:.4g}" if n_val else "")
                  + f" ({time.perf_counter() - start:.1f} s)", flush=True)
    cfg_dict = asdict(cfg)
    model = to_model(net, mean, scale, cfg.output_transform, history, cfg_dict)
    return (model, net) if return_net else model
