"""Griffe extension: render the Sphinx roles of balustrade's docstrings as checked links.

balustrade's docstrings cross-reference with Sphinx roles (``:class:`~balustrade.dsl.ocp.OCP```,
``:func:`verify```, ``:mod:`.banded```). mkdocstrings reads Markdown, where such a role would show
up as literal text. This extension rewrites each role, once the package is loaded, into an
autorefs link ``[`OCP`][balustrade.dsl.ocp.OCP]`` when the name resolves (in the scope of the
docstring, as Python would resolve it there) to a public object of the package; autorefs then
checks that the link lands on a rendered object, so ``mkdocs build --strict`` fails on a link
that breaks later. A role that spells out a public ``balustrade.`` path always becomes a link, so
a renamed or moved target fails the build too. A role naming something outside the package
(numpy, CasADi), a private object or a short name that does not resolve is rendered as code.

Configured in ``mkdocs.yml`` (``plugins.mkdocstrings.handlers.python.options.extensions``).
"""

from __future__ import annotations

import re
from typing import Any

import griffe

ROLE = re.compile(
    r":(?:py:)?(?:class|func|meth|mod|attr|data|exc|obj|const|type):`(?P<tilde>~?)(?P<body>[^`]+)`"
)
PACKAGE = "balustrade"
# names that ``balustrade/__init__.py`` provides lazily through ``__getattr__`` (invisible to a
# static reader); tests/test_docs_examples.py checks that they are the same objects
LAZY = {
    "balustrade.compile": "balustrade.backends.compile",
    "balustrade.verify": "balustrade.testing.verify",
}


def _is_private(path: str) -> bool:
    return any(p.startswith("_") and not p.startswith("__") for p in path.split("."))


class SphinxRoles(griffe.Extension):
    """Rewrite Sphinx roles in every docstring of the package into autorefs links or code."""

    def on_package(self, *, pkg: griffe.Module, loader: griffe.GriffeLoader, **kwargs: Any) -> None:
        if pkg.name != PACKAGE:
            return
        self.loader = loader
        self._walk(pkg, seen=set())

    def _walk(self, obj: griffe.Object, seen: set[str]) -> None:
        if obj.path in seen:
            return
        seen.add(obj.path)
        if obj.docstring is not None:
            obj.docstring.value = ROLE.sub(lambda m: self._render(obj, m), obj.docstring.value)
        for member in obj.members.values():
            if not member.is_alias:
                self._walk(member, seen)

    def _render(self, scope: griffe.Object, match: re.Match[str]) -> str:
        body = match.group("body").strip()
        title, _, explicit = body.partition("<")
        name = (explicit.rstrip(">") if explicit else body).strip()
        title = title.strip() if explicit else name.lstrip(".")
        if match.group("tilde") and not explicit:
            title = title.rsplit(".", 1)[-1]
        path = self._resolve(scope, name.lstrip("."))
        if path is None and name.startswith(PACKAGE + ".") and not _is_private(name):
            path = name  # spelled out in full: let autorefs fail the build if it is broken
        if path is None:
            return f"`{title}`"
        return f"[`{title}`][{path}]"

    def _resolve(self, scope: griffe.Object, name: str) -> str | None:
        """The canonical path of ``name`` seen from ``scope``, if it is a public package object."""
        head, _, rest = name.partition(".")
        try:
            path = scope.resolve(head)
        except Exception:  # noqa: BLE001 - unresolved names are rendered as code
            path = head
        if rest:
            path = f"{path}.{rest}"
        path = LAZY.get(path, path)
        if not path.startswith(PACKAGE + ".") and path != PACKAGE:
            return None
        try:
            found = self.loader.modules_collection[path]
            target = found.final_target if found.is_alias else found
            canonical = target.path
        except Exception:  # noqa: BLE001 - missing members, unresolvable aliases
            return None
        if _is_private(canonical):
            return None
        return canonical
