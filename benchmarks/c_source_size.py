"""Source size and ``-Werror`` build time of an emitted folder (issue #14's must-show).

``python -m benchmarks.c_source_size DIR NAME``: the bytes of every ``.c``/``.h`` file under
``DIR`` (the emitted sources with their ``bal/`` copy) and the wall time of one
:func:`~balustrade.codegen.build` with ``werror=True`` (into ``/tmp``, the folder's own
library is left alone), with the 1-minute load average."""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

from balustrade.codegen import build


def measure(folder: Path, name: str) -> dict[str, float]:
    """``{"mb": source size in MB, "build_s": build time in s, "load": load average}``."""
    size = sum(p.stat().st_size for p in folder.rglob("*") if p.suffix in (".c", ".h"))
    start = time.perf_counter()
    build(folder, name, werror=True, out=Path("/tmp") / f"c_source_size_lib{name}.so")
    return {"mb": size / 1e6, "build_s": time.perf_counter() - start,
            "load": os.getloadavg()[0]}


if __name__ == "__main__":
    m = measure(Path(sys.argv[1]), sys.argv[2])
    print(f"{sys.argv[2]}: C source {m['mb']:.3f} MB, build {m['build_s']:.1f} s with "
          f"-Werror, load {m['load']:.1f}")
