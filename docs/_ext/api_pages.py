"""mkdocs hook: an API reference page for every public subpackage, also for new ones.

docs/api/ holds a hand-written page (a sentence and one ``::: balustrade.<name>`` directive)
for each subpackage and top-level module known when it was written. A subpackage or module
added later, with no directive in any of those pages, gets a generated page
``api/<name>.md`` holding just its directive, listed at the end of the nav's API reference
section: the reference follows the code without anyone remembering to add a page, and its
cross-references are checked like all others.

Configured in ``mkdocs.yml`` (``hooks``).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

PACKAGE = "balustrade"
SECTION = "API reference"
DIRECTIVE = re.compile(rf"^::: ({PACKAGE}(?:\.\w+)?)\s*$", flags=re.M)


def public_modules(root: Path) -> list[str]:
    """``<name>`` of every public subpackage and top-level module of the package."""
    out = []
    for path in sorted((root / PACKAGE).iterdir()):
        name = path.stem if path.suffix == ".py" else path.name
        if name.startswith("_"):
            continue
        if path.suffix == ".py" or (path / "__init__.py").exists():
            out.append(name)
    return out


def missing_pages(root: Path, docs_dir: Path) -> dict[str, str]:
    """``api/<name>.md -> content`` for the public modules no page under docs/api renders."""
    documented = set()
    for page in (docs_dir / "api").glob("*.md"):
        documented |= set(DIRECTIVE.findall(page.read_text()))
    return {f"api/{name}.md": f"# {PACKAGE}.{name}\n\n::: {PACKAGE}.{name}\n"
            for name in public_modules(root) if f"{PACKAGE}.{name}" not in documented}


def _pages(config: Any) -> dict[str, str]:
    return missing_pages(Path(config["config_file_path"]).parent, Path(config["docs_dir"]))


def on_config(config: Any) -> Any:
    for section in config["nav"] or []:
        if isinstance(section, dict) and SECTION in section:
            for uri in _pages(config):
                section[SECTION].append({f"{PACKAGE}.{Path(uri).stem}": uri})
    return config


def on_files(files: Any, config: Any) -> Any:
    from mkdocs.structure.files import File

    for uri, content in _pages(config).items():
        files.append(File.generated(config, uri, content=content))
    return files
