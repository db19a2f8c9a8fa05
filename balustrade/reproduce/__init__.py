"""Reproductions of the thesis' numerical examples, one module each.

A reproduction module defines ``NAMES`` (the names ``balustrade reproduce`` accepts) and
``run(out: pathlib.Path, quick: bool = False) -> dict`` which writes ``metrics.json`` and
PNG plots into ``out`` and returns the metrics. Modules are discovered automatically, so
adding an example means adding one module here.
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Callable
from pathlib import Path

from balustrade.errors import BalustradeError


def registry() -> dict[str, Callable[..., dict]]:
    """Map every reproduction name to its ``run`` function."""
    found: dict[str, Callable[..., dict]] = {}
    for info in pkgutil.iter_modules(__path__):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{__name__}.{info.name}")
        for name in getattr(module, "NAMES", ()):
            found[name] = module.run
    return found


def run(name: str, out: Path, quick: bool = False) -> dict:
    """Run the reproduction ``name`` and write its outputs into ``out``."""
    table = registry()
    if name not in table:
        raise BalustradeError(
            f"unknown reproduction {name!r}; available: {', '.join(sorted(table))}")
    out.mkdir(parents=True, exist_ok=True)
    return table[name](out, quick=quick)
