"""The documentation stays true: marked pages run, the API reference covers the package.

A page of ``docs/`` that contains the marker ``<!-- docs-test`` has every ```` ```python ````
block executed, in order, in one namespace (later blocks use what earlier ones defined), from
a temporary directory. Line numbers in a traceback are those of the Markdown file.
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
MARKER = "<!-- docs-test"
BLOCK = re.compile(r"^```python\n(.*?)^```", flags=re.S | re.M)


def marked_pages() -> list[Path]:
    return sorted(p for p in DOCS.glob("*.md") if MARKER in p.read_text())


def python_blocks(page: Path) -> list[tuple[int, str]]:
    """``(first line, code)`` of every ```python block of ``page`` (lines counted from 1)."""
    text = page.read_text()
    return [(text.count("\n", 0, m.start(1)) + 1, m.group(1)) for m in BLOCK.finditer(text)]


def test_the_formulation_guide_is_marked() -> None:
    pages = [p.name for p in marked_pages()]
    assert "own-formulation.md" in pages
    assert len(python_blocks(DOCS / "own-formulation.md")) >= 6


def test_block_extraction_keeps_line_numbers(tmp_path: Path) -> None:
    page = tmp_path / "p.md"
    page.write_text("# t\n\n```python\nx = 1\n```\n\ntext\n```python\ny = x + 1\n```\n"
                    "```bash\nnot python\n```\n")
    assert python_blocks(page) == [(4, "x = 1\n"), (9, "y = x + 1\n")]


@pytest.mark.parametrize("page", marked_pages(), ids=lambda p: p.name)
def test_marked_page_runs(page: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                          capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": f"docs.{page.stem}"}
    blocks = python_blocks(page)
    assert blocks, f"{page.name} is marked but has no python block"
    for line, code in blocks:
        # pad so that a traceback points at the line of the Markdown file
        exec(compile("\n" * (line - 1) + code, str(page), "exec"), namespace)  # noqa: S102


def _ext_module(name: str):
    """docs/_ext/<name>.py loaded as a module (it is not on the import path)."""
    spec = importlib.util.spec_from_file_location(name, DOCS / "_ext" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _hook():
    """docs/_ext/api_pages.py (the mkdocs hook that generates missing API pages)."""
    return _ext_module("api_pages")


def test_api_reference_pages_are_in_the_nav() -> None:
    """Every hand-written page of docs/api is in the nav (the hook adds generated ones)."""
    nav = (ROOT / "mkdocs.yml").read_text()
    for page in (DOCS / "api").glob("*.md"):
        assert f"api/{page.name}" in nav, page.name


def test_a_new_subpackage_gets_a_generated_page(tmp_path: Path) -> None:
    hook = _hook()
    package = tmp_path / "balustrade"
    for name in ("dsl", "examples", "_private"):
        (package / name).mkdir(parents=True)
        (package / name / "__init__.py").write_text("")
    (package / "errors.py").write_text("")
    (package / "notes").mkdir()                                   # not a package
    (tmp_path / "docs" / "api").mkdir(parents=True)
    (tmp_path / "docs" / "api" / "dsl.md").write_text("# dsl\n\n::: balustrade.dsl\n")
    assert hook.public_modules(tmp_path) == ["dsl", "errors", "examples"]
    pages = hook.missing_pages(tmp_path, tmp_path / "docs")
    assert pages == {"api/errors.md": "# balustrade.errors\n\n::: balustrade.errors\n",
                     "api/examples.md": "# balustrade.examples\n\n::: balustrade.examples\n"}
    config = {"config_file_path": str(tmp_path / "mkdocs.yml"), "docs_dir": str(tmp_path / "docs"),
              "nav": [{"Home": "index.md"}, {"API reference": [{"balustrade.dsl": "api/dsl.md"}]}]}
    hook.on_config(config)
    assert config["nav"][1]["API reference"][1:] == [{"balustrade.errors": "api/errors.md"},
                                                     {"balustrade.examples": "api/examples.md"}]


#: pages kept by another branch, with the table that plays the part of "Where it lives"
WHERE_ELSEWHERE = {"regret.md": "| module |", "engineering.md": "| module |"}


def test_every_guide_page_says_where_things_live() -> None:
    """Each page outside the API reference names the modules holding what it describes
    (as autorefs links where it can, so that ``make docs`` fails when a module moves)."""
    missing = [p.name for p in DOCS.glob("*.md")
               if WHERE_ELSEWHERE.get(p.name, "Where it lives") not in p.read_text()]
    assert missing == []


def test_lazy_names_in_the_reference_are_the_real_objects() -> None:
    """docs/_ext/sphinx_roles.py links ``balustrade.compile``/``verify`` (provided lazily by
    ``balustrade.__getattr__``) to the functions they are."""
    # read, not imported: griffe is installed by `make docs` only
    tree = ast.parse((DOCS / "_ext" / "sphinx_roles.py").read_text())
    lazy = next(ast.literal_eval(node.value) for node in tree.body
                if isinstance(node, ast.Assign) and getattr(node.targets[0], "id", "") == "LAZY")
    import balustrade

    for public, real in lazy.items():
        module, _, attr = real.rpartition(".")
        target = getattr(importlib.import_module(module), attr)
        assert getattr(balustrade, public.rpartition(".")[2]) is target


def _extension():
    """docs/_ext/sphinx_roles.py as a module (its text helpers need no griffe)."""
    return _ext_module("sphinx_roles")


def test_rest_simple_tables_become_markdown() -> None:
    ext = _extension()
    text = ("Intro::\n\n    code\n\n"
            "=========  =====\n"
            "name       what\n"
            "=========  =====\n"
            "``a``      one,\n"
            "           continued\n"
            "``longer_name`` overflows\n"
            "=========  =====\n\nAfter.")
    out = ext._literal_markers(ext._simple_tables(text))
    assert out.split("\n") == ["Intro:", "", "    code", "", "| name | what |", "| --- | --- |",
                               "| ``a`` | one, continued |", "| ``longer_name`` | overflows |",
                               "", "After."]


def test_roles_are_recognized() -> None:
    ext = _extension()
    found = [m.group("tilde", "body") for m in ext.ROLE.finditer(
        "see :class:`~balustrade.dsl.ocp.OCP`, :func:`verify` and :py:mod:`.banded`")]
    assert found == [("~", "balustrade.dsl.ocp.OCP"), ("", "verify"), ("", ".banded")]
