"""docs/engineering.md runs as written: its code blocks, in order, in one namespace."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

DOC = Path(__file__).resolve().parent.parent / "docs" / "engineering.md"


def test_engineering_page_runs(capsys):
    blocks = re.findall(r"```python\n(.*?)```", DOC.read_text(), flags=re.S)
    assert len(blocks) == 5
    namespace: dict = {}
    for k, code in enumerate(blocks):
        exec(compile(code, f"{DOC.name} block {k + 1}", "exec"), namespace)  # noqa: S102
    trace = namespace["trace"]
    assert trace.states.shape == (81, 2) and np.all(np.isfinite(trace.states))
    assert namespace["csv_path"].exists() and (namespace["out"] / "cart.png").exists()
    assert capsys.readouterr().out.startswith("k,x[0],x[1],u[0],u_p[0]")
