"""Training ``ĥ`` with PyTorch and exporting it to CasADi (Section 7.2, DESIGN.md)."""

from __future__ import annotations

import subprocess
import sys

import casadi as ca
import numpy as np
import pytest
import torch

from balustrade.errors import BalustradeError
from balustrade.learn.export import evaluate, expression, to_casadi
from balustrade.learn.train import MLPModel, TrainConfig, train


def data(n: int = 1500, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    X = rng.uniform([-2.0, -8.0], [2.0, 8.0], (n, 2))
    y = np.maximum(0.0, np.abs(X[:, 0]) - 0.5) * 4 + 0.1 * X[:, 1] ** 2 - 0.3
    return X, y


def torch_eval(net, model: MLPModel, X: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        out = net(torch.from_numpy((X - model.mean) / model.scale)).numpy().reshape(-1)
    return out ** 3 if model.output_transform == "cbrt" else out


@pytest.mark.parametrize("widths,transform", [((4, 4), None), ((16, 16, 16), "cbrt"),
                                              ((32, 8), None)])
def test_exported_network_equals_pytorch_float64(widths, transform):
    X, y = data()
    model, net = train(X, y, TrainConfig(widths=widths, epochs=2, batch_size=64, lr=1e-2,
                                         output_transform=transform), return_net=True)
    rng = np.random.default_rng(1)
    Z = rng.uniform([-2.5, -9.0], [2.5, 9.0], (10_000, 2))
    ref = torch_eval(net, model, Z)
    fn = to_casadi(model)
    assert np.max(np.abs(evaluate(fn, Z) - ref)) <= 1e-10
    assert np.max(np.abs(model(Z) - ref)) <= 1e-10
    # far away, where softplus is linear (threshold 20): relative agreement
    far = rng.uniform(-300, 300, (1000, 2))
    ref_far = torch_eval(net, model, far)
    np.testing.assert_allclose(evaluate(fn, far), ref_far, rtol=1e-12, atol=1e-10)
    # gradients too (what IPOPT uses in (7.5)/(7.6))
    x = ca.SX.sym("x", 2)
    grad = ca.Function("g", [x], [ca.gradient(expression(model, x), x)])
    zt = torch.from_numpy(Z[:200].copy()).requires_grad_(True)
    out = net((zt - torch.from_numpy(model.mean)) / torch.from_numpy(model.scale)).reshape(-1)
    out = out ** 3 if transform == "cbrt" else out
    out.sum().backward()
    g_ref = zt.grad.numpy()
    g = np.array([np.asarray(grad(z)).reshape(-1) for z in Z[:200]])
    np.testing.assert_allclose(g, g_ref, rtol=1e-9, atol=1e-10)


def test_training_is_seeded_and_learns():
    X, y = data()
    cfg = TrainConfig(widths=(8, 8), epochs=15, batch_size=32, lr=1e-2, seed=3)
    a, b = train(X, y, cfg), train(X, y, cfg)
    assert all(np.array_equal(u, v) for u, v in zip(a.weights, b.weights))
    c = train(X, y, TrainConfig(widths=(8, 8), epochs=15, batch_size=32, lr=1e-2, seed=4))
    assert not np.array_equal(a.weights[0], c.weights[0])
    hist = a.history
    assert len(hist["train_loss"]) == 15 and hist["val_loss"][-1] < 0.2 * hist["val_loss"][0]
    assert hist["val_mse_h"][-1] < 0.1 * np.var(y)
    huber = train(X, y, TrainConfig(widths=(8,), epochs=3, loss="huber", batch_size=64))
    assert np.all(np.isfinite(huber(X)))
    assert [W.shape for W in huber.weights] == [(8, 2), (1, 8)]


def test_cosine_learning_rate_schedule():
    X, y = data()
    base = dict(widths=(8, 8), epochs=15, batch_size=32, lr=1e-2, seed=1)
    const = train(X, y, TrainConfig(**base))
    cos = train(X, y, TrainConfig(**base, lr_schedule="cosine"))
    assert const.history["lr"] == [1e-2] * 15
    lr = np.array(cos.history["lr"])
    assert np.all(np.diff(lr) < 0) and lr[-1] <= 1e-12  # annealed to 0 over all steps
    expected = 1e-2 * 0.5 * (1 + np.cos(np.pi * np.arange(1, 16) / 15))  # end of epoch e
    np.testing.assert_allclose(lr[:-1], expected[:-1], rtol=1e-9)
    assert not np.array_equal(const.weights[0], cos.weights[0])
    assert cos.config["lr_schedule"] == "cosine"
    assert cos.history["val_loss"][-1] < 0.5 * cos.history["val_loss"][0]
    with pytest.raises(BalustradeError):
        TrainConfig(lr_schedule="step")


def test_cube_root_transform_and_save_load(tmp_path):
    X, y = data()
    y = y ** 3 * 10                      # large dynamic range, as h_PB outside S_PB
    model = train(X, y, TrainConfig(widths=(16, 16), epochs=20, batch_size=32, lr=1e-2,
                                     output_transform="cbrt"))
    pred = model(X)
    assert np.corrcoef(pred, y)[0, 1] > 0.9
    path = tmp_path / "m.npz"
    model.save(path)
    loaded = MLPModel.load(path)
    assert loaded.output_transform == "cbrt" and loaded.history == model.history
    np.testing.assert_array_equal(loaded(X), pred)


def test_exported_network_runs_in_the_approximate_filter():
    from balustrade.control.approximate import ApproximatePCBFFilter
    from balustrade.models.pendulum import pendulum, pendulum_setup

    X, y = data()
    model = train(X, y, TrainConfig(widths=(4, 4), epochs=3, batch_size=64))
    ctl = ApproximatePCBFFilter(pendulum(), pendulum_setup().U, to_casadi(model), rho=0.5)
    for x in np.random.default_rng(0).uniform([-0.5, -1.5], [0.5, 1.5], (20, 2)):
        u, info = ctl.step(x, np.array([2.0]))
        assert info.fallback is None and abs(u[0]) <= 3 + 1e-7


def test_everything_but_training_imports_without_torch():
    code = (
        "import importlib.abc, sys\n"
        "class NoTorch(importlib.abc.MetaPathFinder):\n"
        "    def find_spec(self, name, path, target=None):\n"
        "        if name.split('.')[0] == 'torch':\n"
        "            raise ImportError('torch is not installed')\n"
        "sys.meta_path.insert(0, NoTorch())\n"
        "import balustrade.learn.sampler, balustrade.learn.dataset, balustrade.learn.export\n"
        "import balustrade.learn.executors, balustrade.learn.cli, balustrade.learn.progress\n"
        "import balustrade.problems.approximate, balustrade.control.approximate\n"
        "import balustrade.reproduce.pendulum_approx\n"
        "from balustrade.cli import build_parser; build_parser()\n"
        "import numpy as np\n"
        "from balustrade.learn.train import train\n"
        "from balustrade.errors import BalustradeError\n"
        "try:\n"
        "    train(np.zeros((4, 2)), np.zeros(4))\n"
        "except BalustradeError as e:\n"
        "    print('refused:', e)\n"
        "assert 'torch' not in sys.modules\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "refused: training needs PyTorch" in out.stdout


def test_cli_sample_then_train(tmp_path):
    from balustrade.cli import main

    data_dir, model_path = tmp_path / "d", tmp_path / "h.npz"
    assert main(["sample", "--out", str(data_dir), "--lower", "-0.6", "-2", "--upper", "0.6",
                 "2", "--grid-step", "0.2", "0.5", "--workers", "1", "--quiet"]) == 0
    assert main(["train", "--data", str(data_dir), "--out", str(model_path), "--widths", "4",
                 "4", "--epochs", "2", "--batch-size", "16", "--quiet"]) == 0
    model = MLPModel.load(model_path)
    assert model.nx == 2 and len(model.weights) == 3
    assert list(model.config["widths"]) == [4, 4]
