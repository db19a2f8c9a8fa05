"""docs/adaptive.md's set-membership code block runs as written and prints what its comment
says (audit session 13, finding 7: the comment said "4 LPs (2q)" while it printed 0 — the
box update of a 2-parameter chain takes its bounds from vertices, no LP)."""

from __future__ import annotations

import contextlib
import io
import re
from pathlib import Path

DOC = Path(__file__).resolve().parents[1] / "docs" / "adaptive.md"


def _block() -> str:
    blocks = re.findall(r"```python\n(.*?)```", DOC.read_text(), flags=re.S)
    (block,) = [b for b in blocks if "last = box.history[-1]" in b]
    return block


def test_set_membership_block_prints_its_comment() -> None:
    block = _block()
    line = next(ln for ln in block.splitlines() if ln.startswith("print(last.status"))
    claimed = int(re.search(r"(\d+) LPs", line).group(1))
    out, ns = io.StringIO(), {}
    with contextlib.redirect_stdout(out):
        exec(compile(block, str(DOC), "exec"), ns)       # noqa: S102 - the doc's own code
    last = ns["last"]
    assert str(getattr(last.status, "value", last.status)) == "updated"
    assert max(last.width) < 0.2 / 100                   # "widths ≪ 0.2"
    assert last.lps == claimed, (last.lps, line)
