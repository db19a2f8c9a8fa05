"""Solver choice is data owned by ``balustrade/backends/`` (issue #13 §1): no module outside
it names a solver or a solver option — not in code, comments or docstrings. Code elsewhere
speaks of targets and presets (``"fast-sqp"``, ``"exact"``, …,
:mod:`balustrade.backends.targets`).

The check is the grep of the issue, case-insensitive, over ``balustrade/**/*.py`` without
``backends/``; a failure lists ``file:line: text``.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "balustrade"

#: solver names and solver options (the grep of issue #13)
PATTERN = re.compile(r"ipopt|sqpmethod|qrqp|clarabel|piqp|osqp|scs|fatrop|hpipm|ecos|daqp|"
                     r"max_iter|print_level|mu_strategy|convexify", re.IGNORECASE)

#: files other work of issue #13 is rewriting right now, with the reason; the merge empties
#: this list (an entry without hits fails below, so it cannot go stale)
KNOWN: dict[str, str] = {}


def violations(root: Path = ROOT) -> dict[str, list[str]]:
    """``{relative path: ["path:line: text", …]}`` for every ``.py`` file under ``root``
    outside ``backends/`` that names a solver or a solver option."""
    found: dict[str, list[str]] = {}
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root).as_posix()
        if rel.startswith("backends/"):
            continue
        for k, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            if PATTERN.search(line):
                found.setdefault(rel, []).append(f"balustrade/{rel}:{k}: {line.strip()}")
    return found


def test_no_solver_names_outside_backends():
    bad = {rel: lines for rel, lines in violations().items() if rel not in KNOWN}
    assert not bad, "solver names outside balustrade/backends/ (use a target or preset):\n" \
        + "\n".join(line for lines in bad.values() for line in lines)


def test_known_exceptions_are_not_stale():
    found = violations()
    stale = [rel for rel in KNOWN if rel not in found]
    assert not stale, f"no solver names left in {stale}: remove them from KNOWN"


@pytest.mark.parametrize("planted", ['    return compile(ocp, "casadi", "ipopt")\n',
                                     '# the options {"max_iter": 500} go to the SQP\n',
                                     '"""Solved by CLARABEL."""\n'])
def test_a_planted_solver_name_is_found(tmp_path, planted):
    (tmp_path / "control").mkdir()
    (tmp_path / "backends").mkdir()
    (tmp_path / "control" / "mine.py").write_text("x = 1\n" + planted)
    (tmp_path / "backends" / "ok.py").write_text(planted)  # allowed there
    assert violations(tmp_path) == {
        "control/mine.py": [f"balustrade/control/mine.py:2: {planted.strip()}"]}
