"""The layering of DESIGN.md, checked on the source: every module under ``balustrade/`` is
parsed with :mod:`ast`, mapped to its layer (its first folder, or the top-level module),
and each import — at module level or inside a function — must be allowed by the table.

=============  =====================================================  ======================
layer          may import (balustrade layers)                         may not import
=============  =====================================================  ======================
``errors``     —                                                      —
``_checks``    errors                                                 cvxpy
``dsl``        dsl, errors, _checks                                   cvxpy
``backends``   backends, dsl, errors, _checks                         —
``problems``   problems, dsl, errors, _checks                         cvxpy
``design``     design, backends, problems, dsl, errors, _checks       cvxpy
``models``     models, dsl, errors, _checks                           cvxpy
``control``    control, estimate, backends, problems, dsl, errors,    cvxpy
               _checks
``codegen``    codegen, backends, control, dsl, errors, _checks       cvxpy
``learn``      learn, backends, dsl, errors, _checks, cli             —
``estimate``   estimate, backends, dsl, errors, _checks               cvxpy
``testing``    backends, dsl, errors, _checks                         —
``examples``   everything but reproduce and cli                       —
``reproduce``  everything but cli                                     —
``cli``        everything                                             —
(package)      errors, backends, testing (``balustrade/__init__.py``)  —
=============  =====================================================  ======================

So: the language knows nothing of solvers or formulations; formulations and models import
only the language (no backend, no controller, no cvxpy: a synthesis problem is written in the
language and lowered by ``backends/``); ``learn/`` defines no model; controllers and codegen
never call cvxpy themselves. :data:`KNOWN` lists the violations other work is removing right
now, each with its reason; an entry that is no longer a violation fails the test, so the
list only shrinks.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "balustrade"

BASE = {"errors", "_checks"}
ALL = {"errors", "_checks", "dsl", "backends", "problems", "design", "models", "control",
       "codegen", "learn", "estimate", "testing", "examples", "reproduce", "cli",
       "__init__"}

#: layer -> (balustrade layers it may import, third-party packages it may not import)
RULES: dict[str, tuple[set[str], set[str]]] = {
    "errors": (set(), set()),
    "_checks": ({"errors"}, {"cvxpy"}),
    "dsl": ({"dsl"} | BASE, {"cvxpy"}),
    "backends": ({"backends", "dsl"} | BASE, set()),
    "problems": ({"problems", "dsl"} | BASE, {"cvxpy"}),
    "design": ({"design", "backends", "problems", "dsl"} | BASE, {"cvxpy"}),
    "models": ({"models", "dsl"} | BASE, {"cvxpy"}),
    "control": ({"control", "estimate", "backends", "problems", "dsl"} | BASE, {"cvxpy"}),
    "codegen": ({"codegen", "backends", "control", "dsl"} | BASE, {"cvxpy"}),
    "learn": ({"learn", "backends", "dsl", "cli"} | BASE, set()),
    "estimate": ({"estimate", "backends", "dsl"} | BASE, {"cvxpy"}),
    "testing": ({"backends", "dsl"} | BASE, set()),
    "examples": (ALL - {"reproduce", "cli"}, set()),
    "reproduce": (ALL - {"cli"}, set()),
    "cli": (ALL, set()),
    "__init__": ({"errors", "backends", "testing"}, set()),
}

#: (module, imported layer or package) -> why it is still there; the merge empties this
KNOWN: dict[tuple[str, str], str] = {}


def layer_of(rel: Path) -> str:
    """``dsl/sets.py`` -> ``dsl``; ``cli.py`` -> ``cli``; ``__init__.py`` -> ``__init__``."""
    return rel.parts[0] if len(rel.parts) > 1 else rel.stem


def imports_of(path: Path, rel: Path) -> list[tuple[str, int]]:
    """``(target, line)`` for every import in the file: a balustrade layer for imports of
    the package, the top-level package name otherwise."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    package = ["balustrade", *rel.parts[:-1]]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against the module's package
                base = package[: len(package) - node.level + 1]
                names = [".".join([*base, *([node.module] if node.module else [])])]
            else:
                names = [node.module or ""]
            if names[0] == "balustrade":  # from balustrade import x
                names = [f"balustrade.{a.name}" for a in node.names]
        else:
            continue
        for name in names:
            parts = name.split(".")
            if parts[0] != "balustrade":
                out.append((parts[0], node.lineno))
            elif len(parts) == 1:
                out.append(("__init__", node.lineno))
            else:
                out.append((parts[1] if parts[1] in ALL else "__init__", node.lineno))
    return out


def violations(root: Path) -> dict[tuple[str, str], list[str]]:
    """``(module, target) -> ["module:line: rule", ...]`` for every forbidden import."""
    found: dict[tuple[str, str], list[str]] = {}
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root)
        layer = layer_of(rel)
        if layer not in RULES:
            found.setdefault((rel.as_posix(), "<layer>"), []).append(
                f"{rel}: layer {layer!r} is not in the rule table")
            continue
        allowed, banned = RULES[layer]
        for target, line in imports_of(path, rel):
            if target in ALL:
                bad = target != layer and target not in allowed
                why = f"{layer} may not import balustrade.{target}"
            else:
                bad = target in banned
                why = f"{layer} may not import {target}"
            if bad:
                found.setdefault((rel.as_posix(), target), []).append(f"{rel}:{line}: {why}")
    return found


def test_rule_table_covers_every_layer():
    assert set(RULES) == ALL
    layers = {layer_of(p.relative_to(ROOT)) for p in ROOT.rglob("*.py")}
    assert layers <= set(RULES), f"new layer(s) without rules: {layers - set(RULES)}"


def test_every_import_follows_the_layering():
    found = violations(ROOT)
    new = [msg for key, msgs in found.items() if key not in KNOWN for msg in msgs]
    assert not new, "imports that break the layering (DESIGN.md):\n" + "\n".join(new)


def test_known_violations_are_still_violations():
    """When a KNOWN violation is removed, remove its entry too: the list only shrinks."""
    found = violations(ROOT)
    stale = [f"{k}: {why}" for k, why in KNOWN.items() if k not in found]
    assert not stale, "KNOWN entries that no longer occur (delete them):\n" + "\n".join(stale)


@pytest.mark.parametrize("layer,code,target", [
    ("problems", "from balustrade.backends import compile\n", "backends"),
    ("problems", "def f():\n    from balustrade.control.base import StepInfo\n", "control"),
    ("problems", "import cvxpy as cp\n", "cvxpy"),
    ("models", "from balustrade.problems.robust import robust_sets\n", "problems"),
    ("dsl", "import cvxpy\n", "cvxpy"),
    ("dsl", "from ..backends import compile\n", "backends"),
    ("learn", "from balustrade.models.pendulum import pendulum\n", "models"),
    ("backends", "from balustrade.problems import mpc\n", "problems"),
    ("control", "import cvxpy\n", "cvxpy"),
    ("estimate", "from balustrade.control.base import simulate\n", "control"),
    ("estimate", "import cvxpy\n", "cvxpy"),
])
def test_a_planted_violation_is_caught(tmp_path, layer, code, target):
    pkg = tmp_path / "balustrade"
    (pkg / layer).mkdir(parents=True)
    (pkg / layer / "planted.py").write_text("from __future__ import annotations\n" + code)
    (pkg / layer / "fine.py").write_text(f"from balustrade.{layer} import planted\n"
                                         "from balustrade.errors import BalustradeError\n"
                                         "import numpy\n")
    found = violations(pkg)
    assert list(found) == [(f"{layer}/planted.py", target)], found
