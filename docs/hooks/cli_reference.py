"""MkDocs hook: fill the CLI reference page from the command line itself.

``reference/cli.md`` holds a marker line; at build time it is replaced by the Markdown that
:func:`pidlab.cli.clidoc.cli_markdown` generates from ``pidlab.cli.main.app``, so the page shows exactly
the commands, arguments, options and defaults of the installed command line.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

PAGE = "reference/cli.md"
MARKER = "<!-- cli-reference -->"

log = logging.getLogger("mkdocs.hooks.cli_reference")


def on_page_markdown(markdown: str, page: Any, config: Any, files: Any) -> str:
    """Replace the marker line of the CLI reference page by the generated reference."""
    if page.file.src_uri != PAGE:
        return markdown
    if MARKER not in markdown:
        log.warning("%s: no %s line to replace with the CLI reference", PAGE, MARKER)
        return markdown
    from pidlab.cli.clidoc import cli_markdown

    return markdown.replace(MARKER, cli_markdown().rstrip("\n"), 1)


def on_serve(server: Any, config: Any, builder: Any) -> Any:
    """``mkdocs serve``: rebuild when the command line's source changes."""
    server.watch(str(Path(config["config_file_path"]).parent / "pidlab" / "cli.py"))
    return server
