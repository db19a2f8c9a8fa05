"""The README's quickstart runs as written."""

from __future__ import annotations

import re
from pathlib import Path


def test_readme_quickstart_runs(capsys):
    text = (Path(__file__).resolve().parent.parent / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    assert len(blocks) >= 2
    namespace: dict = {}
    for code in blocks:
        exec(compile(code, "README.md", "exec"), namespace)  # noqa: S102
    assert namespace["a"].objective > 0
    assert abs(namespace["a"].objective - namespace["b"].objective) <= 1e-6
