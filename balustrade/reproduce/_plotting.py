"""Small matplotlib helpers shared by the reproductions (headless backend)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def figure(rows: int, cols: int = 1, size: tuple[float, float] = (7.0, 7.0)):
    """A figure with a grid of axes (squeezed like ``plt.subplots``)."""
    return plt.subplots(rows, cols, figsize=size, constrained_layout=True)


def save(fig, path: Path) -> str:
    """Write ``fig`` as PNG and close it; returns the path as a string."""
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return str(path)
