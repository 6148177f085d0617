"""Griffe extension: the reST idioms of pidlab's docstrings, read as Markdown.

mkdocstrings reads docstrings as Markdown; pidlab's also use three reST idioms, rewritten here
before a docstring is parsed:

- cross-reference roles (``:func:`pidlab.plant.model.load_model```,
  ``:class:`~pidlab.controller.spec.CoachSpec```)
  become *optional* cross-references of mkdocs-autorefs: a link when the target is documented on
  the site, plain code otherwise (never a build warning). Unqualified names are looked up in the
  docstring's scope (``:func:`load_spec``` inside ``pidlab.controller.spec``);
- a paragraph ending in ``::`` before an indented literal block ends in ``:`` (the block is
  Markdown's indented code block already);
- definition lists in the free text before the numpydoc sections (a short term line, then its
  indented definition) become Markdown definition lists (the ``def_list`` extension).
"""

from __future__ import annotations

import html
import re
from typing import Any

import griffe

ROLE = re.compile(r":(?:py:)?(?:func|class|meth|attr|mod|data|exc|obj|const|type):`(?P<text>[^`]+)`")


def _identifier(obj: Any, target: str) -> str:
    """The full path of ``target`` as seen from ``obj`` (``target`` itself if it cannot be resolved)."""
    if target.startswith("pidlab."):
        return target
    head, _, rest = target.partition(".")
    scope = obj if obj.is_class or obj.is_module else obj.parent
    try:
        resolved = scope.resolve(head) if scope is not None else target
    except Exception:  # griffe raises NameResolutionError; anything else: keep the name as written
        return target
    return f"{resolved}.{rest}" if rest else resolved


def rewrite_roles(obj: Any, text: str) -> str:
    """Replace every reST role of ``text`` by an optional autorefs cross-reference."""

    def replace(match: re.Match[str]) -> str:
        raw = match["text"].strip()
        explicit = re.fullmatch(r"(?P<title>.+?)\s*<(?P<target>[^>]+)>", raw)
        if explicit:
            title, target = explicit["title"], explicit["target"]
        else:
            target = raw.lstrip("~!")
            title = target.rsplit(".", 1)[-1] if raw.startswith("~") else target
        identifier = _identifier(obj, target.removesuffix("()"))
        return (
            f'<autoref identifier="{html.escape(identifier)}" optional>'
            f"<code>{html.escape(title)}</code></autoref>"
        )

    return ROLE.sub(replace, text)


SECTION_RULE = re.compile(r"-{3,}")
TERM_MAX = 40  # longer unindented lines followed by indented ones are wrapped text, not terms


def rewrite_blocks(text: str) -> str:
    """Literal-block markers and definition lists of the free text (before any numpydoc section)."""
    lines = text.split("\n")
    out: list[str] = []
    i = 0
    while i < len(lines):
        line = lines[i]
        nxt = lines[i + 1] if i + 1 < len(lines) else ""
        if SECTION_RULE.fullmatch(nxt.strip()) and line.strip():
            out += lines[i:]  # numpydoc sections: griffe parses those itself
            break
        if line.rstrip().endswith("::") and not nxt.strip():
            stripped = line.rstrip()[:-2].rstrip()
            if stripped:
                out.append(stripped + ":")
            i += 1
            continue
        is_term = (
            line.strip()
            and not line.startswith(" ")
            and len(line) <= TERM_MAX
            and not line.startswith(("(", "-", "*", ">>>"))
            and nxt.startswith("    ")
            and nxt.strip()
        )
        if is_term:
            out.append(line)
            j = i + 1
            first = True
            while j < len(lines) and lines[j].startswith("    ") and lines[j].strip():
                out.append((":   " if first else "    ") + lines[j].strip())
                first = False
                j += 1
            out.append("")
            i = j
            continue
        out.append(line)
        i += 1
    return "\n".join(out)


class RestIdioms(griffe.Extension):
    """Rewrite the reST idioms of every docstring (see the module docstring)."""

    def on_object(self, *, obj: griffe.Object, loader: griffe.GriffeLoader, **kwargs: Any) -> None:
        """Rewrite ``obj``'s docstring once the object tree is complete."""
        if obj.docstring is not None:
            obj.docstring.value = rewrite_blocks(rewrite_roles(obj, obj.docstring.value))
