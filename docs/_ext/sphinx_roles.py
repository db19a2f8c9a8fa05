"""Griffe extension: render the reST of balustrade's docstrings as Markdown, roles as checked links.

balustrade's docstrings cross-reference with Sphinx roles (``:class:`~balustrade.dsl.ocp.OCP```,
``:func:`verify```, ``:mod:`.banded```). mkdocstrings reads Markdown, where such a role would show
up as literal text. This extension rewrites each role, once the package is loaded, into an
autorefs link ``[`OCP`][balustrade.dsl.ocp.OCP]`` when the name resolves (in the scope of the
docstring, as Python would resolve it there) to a public object of the package; autorefs then
checks that the link lands on a rendered object, so ``mkdocs build --strict`` fails on a link
that breaks later. A role that spells out a public ``balustrade.`` path always becomes a link, so
a renamed or moved target fails the build too. A role naming something outside the package
(numpy, CasADi), a private object or a short name that does not resolve is rendered as code.

Two more reST constructs are translated so that they read well: simple tables (``====  ====``
borders) become Markdown tables, and a paragraph ending in ``::`` (an indented literal block
follows, which Markdown also shows as code) loses one colon.

Configured in ``mkdocs.yml`` (``plugins.mkdocstrings.handlers.python.options.extensions``).
"""

from __future__ import annotations

import re
from typing import Any

try:
    import griffe
except ImportError:  # the docs extra is not installed: the text helpers stay testable
    griffe = None

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


class SphinxRoles(griffe.Extension if griffe else object):  # type: ignore[misc]
    """Rewrite Sphinx roles in every docstring of the package into autorefs links or code."""

    def on_package(self, *, pkg: griffe.Module, loader: griffe.GriffeLoader, **kwargs: Any) -> None:
        if pkg.name != PACKAGE:
            return
        self.loader = loader
        self._walk(pkg, seen=set())
        self._hide_reexports(pkg)

    def _walk(self, obj: griffe.Object, seen: set[str]) -> None:
        if obj.path in seen:
            return
        seen.add(obj.path)
        if obj.docstring is not None:
            text = ROLE.sub(lambda m: self._render(obj, m), obj.docstring.value)
            obj.docstring.value = _literal_markers(_simple_tables(text))
        for member in obj.members.values():
            if not member.is_alias:
                self._walk(member, seen)

    def _hide_reexports(self, module: griffe.Module) -> None:
        """Document each object once, in the module that defines it: a name a package (or a
        module) re-exports from a public module of balustrade is not rendered again there."""
        for member in list(module.members.values()):
            if member.is_alias:
                try:
                    canonical = member.final_target.path
                except Exception:  # noqa: BLE001 - unresolvable: leave it to mkdocstrings
                    continue
                if canonical.startswith(PACKAGE + ".") and not _is_private(canonical):
                    member.public = False
            elif member.is_module:
                self._hide_reexports(member)

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


BORDER = re.compile(r"^(?P<indent>\s*)=+(?: +=+)+\s*$")


def _cells(line: str, starts: list[int]) -> list[str]:
    """Split a table row at the column starts; text overflowing a column moves the cut to
    the next space (as reST allows for the last columns)."""
    cuts, pos = [], 0
    for start in starts[1:]:
        start = max(start, pos)
        while 0 < start < len(line) and not line[start - 1].isspace():
            start += 1
        cuts.append(start)
        pos = start
    bounds = [0, *cuts, len(line)]
    return [line[a:b].strip() for a, b in zip(bounds, bounds[1:])]


def _simple_tables(text: str) -> str:
    """reST simple tables (``====  ====`` borders, optional header) as Markdown tables."""
    lines, out, i = text.split("\n"), [], 0
    while i < len(lines):
        match = BORDER.match(lines[i])
        if not match:
            out.append(lines[i])
            i += 1
            continue
        border, indent = lines[i], len(match.group("indent"))
        starts = [m.start() - indent for m in re.finditer(r"=+", border)]
        borders, rows, j = [i], [], i + 1
        while j < len(lines) and len(borders) < 3:
            if BORDER.match(lines[j]):
                borders.append(j)
                if j + 1 >= len(lines) or not lines[j + 1].strip():
                    break  # a closing border: nothing but a blank line follows
            elif lines[j].strip():
                rows.append((j, _cells(lines[j][indent:], starts)))
            j += 1
        merged: list[list[str]] = []
        for _, cells in rows:
            if merged and not cells[0]:  # continuation line of the previous row
                merged[-1] = [f"{a} {b}".strip() for a, b in zip(merged[-1], cells)]
            else:
                merged.append(cells)
        header_rows = [c for k, c in rows if k < borders[1]] if len(borders) == 3 else []
        header = header_rows[0] if header_rows else [" "] * len(starts)
        body = merged[len(header_rows):]
        out.append("| " + " | ".join(header) + " |")
        out.append("|" + " --- |" * len(starts))
        out.extend("| " + " | ".join(c.replace("|", "\\|") for c in row) + " |" for row in body)
        i = borders[-1] + 1
    return "\n".join(out)


def _literal_markers(text: str) -> str:
    """``text::`` before an indented literal block reads ``text:``; a lone ``::`` goes."""
    text = re.sub(r"(?m)^[ \t]*::[ \t]*$", "", text)
    return re.sub(r"(?m)(\S)::[ \t]*$", r"\1:", text)
