"""Markdown reference of the ``pidlab`` command line, generated from the command line itself.

The documentation site fills its CLI reference page with :func:`cli_markdown` at build time
(``docs/hooks/cli_reference.py``), so the page always lists the commands, arguments, options and
defaults that ``pidlab --help`` shows.

Examples
--------
>>> from pidlab.cli.clidoc import cli_markdown
>>> text = cli_markdown()
>>> "## `pidlab train`" in text
True
"""

from __future__ import annotations

import html
import inspect
from typing import Any

__all__ = ["cli_markdown", "command_markdown"]

# Characters that Python-Markdown would otherwise read as markup in free text.
_MARKUP = str.maketrans({c: "\\" + c for c in "\\`*_[]|"})


def _text(value: str) -> str:
    """Escape free text (help strings) for Markdown, table cells included."""
    return html.escape(value, quote=False).translate(_MARKUP)


def _code(value: str) -> str:
    """Format ``value`` as inline code that is safe inside a table cell."""
    fence = "``" if "`" in value else "`"
    pad = " " if value.startswith("`") or value.endswith("`") else ""
    # Python-Markdown's tables do not split cells at a | inside a code span (and keep a backslash).
    return f"{fence}{pad}{value}{pad}{fence}"


def _help_text(command: Any) -> str:
    """A command's help text, as ``--help`` shows it (cut at click's form feed marker)."""
    text = command.help or command.short_help or ""
    text = text.split("\f", 1)[0]
    return inspect.cleandoc(text).replace("\b\n", "")


def _context(command: Any, name: str, parent: Any | None) -> Any:
    """A click context for ``command``, as the command line would create it (help option names...)."""
    import typer

    return typer.Context(command, info_name=name, parent=parent, **(command.context_settings or {}))


def _is_help_option(param: Any, ctx: Any) -> bool:
    help_option = ctx.command.get_help_option(ctx)
    return help_option is not None and param is help_option


def _param_names(param: Any) -> str:
    """The names of a parameter: the metavar of an argument, every spelling of an option."""
    if param.param_type_name == "argument":
        return _code(param.metavar or param.name.upper())
    # Short spellings first (-h / --help), as click lists them.
    opts = sorted(param.opts, key=lambda opt: opt.startswith("--"))
    return " / ".join(_code(opt) for opt in [*opts, *param.secondary_opts])


def _param_type(param: Any, ctx: Any) -> str:
    """The value a parameter takes: an option's metavar, the type, or ``flag`` for boolean switches."""
    if getattr(param, "is_flag", False) and param.param_type_name == "option":
        return "flag"
    if param.metavar and param.param_type_name == "option":
        label = param.metavar
    elif hasattr(param, "display_type"):
        label = param.display_type(ctx).strip("<>")
    else:
        label = param.type.name
    if param.nargs != 1 and not param.multiple:
        label += " ..."
    return _code(label) + (", repeatable" if param.multiple else "")


def _param_default(param: Any, ctx: Any) -> str:
    """The default of a parameter, or *required*, or an empty cell when there is none."""
    if param.required:
        return "*required*"
    if _is_help_option(param, ctx):
        return ""
    default = param.get_default(ctx, call=False)
    if callable(default):
        return "*(dynamic)*"
    if getattr(param, "is_flag", False) and param.param_type_name == "option":
        if param.secondary_opts:
            return _code(param.opts[0] if default else param.secondary_opts[0])
        return _code("true") if default else _code("false")
    if default is None or default == () or default == []:
        return ""
    if isinstance(default, (list, tuple)):
        return ", ".join(_code(str(item)) for item in default)
    return _code(str(default))


def _usage(command: Any, ctx: Any) -> str:
    """The usage line: command path, ``[OPTIONS]``, then the arguments."""
    pieces = [ctx.command_path]
    params = [p for p in command.get_params(ctx) if not getattr(p, "hidden", False)]
    if any(p.param_type_name == "option" for p in params):
        pieces.append("[OPTIONS]")
    for param in params:
        if param.param_type_name != "argument":
            continue
        name = param.metavar or param.name.upper()
        if param.nargs != 1:
            name += "..."
        pieces.append(name if param.required else f"[{name}]")
    if hasattr(command, "commands"):
        pieces.append(getattr(command, "subcommand_metavar", None) or "COMMAND [ARGS]...")
    return " ".join(pieces)


def _param_table(command: Any, ctx: Any, with_help: bool) -> list[str]:
    """Markdown table of a command's arguments and options (the help option only if ``with_help``)."""
    rows = [
        "| Name | Type | Default | Description |",
        "| --- | --- | --- | --- |",
    ]
    count = 0
    for param in command.get_params(ctx):
        if getattr(param, "hidden", False) or (not with_help and _is_help_option(param, ctx)):
            continue
        description = _text(" ".join((getattr(param, "help", None) or "").split()))
        cells = [_param_names(param), _param_type(param, ctx), _param_default(param, ctx), description]
        rows.append("| " + " | ".join(cells) + " |")
        count += 1
    return rows if count else []


def _section(command: Any, ctx: Any, level: int, with_help: bool) -> list[str]:
    """Heading, help text, usage line and parameter table of one command (no subcommands)."""
    lines = [f"{'#' * level} `{ctx.command_path}`", ""]
    help_text = _help_text(command)
    if help_text:
        lines += [_text(help_text), ""]
    lines += ["```text", _usage(command, ctx), "```", ""]
    table = _param_table(command, ctx, with_help)
    if table:
        lines += [*table, ""]
    return lines


def _subcommands(command: Any, ctx: Any) -> list[tuple[str, Any]]:
    """The visible subcommands of a group, in the order ``--help`` lists them."""
    if not hasattr(command, "commands"):
        return []
    found = [(name, command.get_command(ctx, name)) for name in command.list_commands(ctx)]
    return [(name, sub) for name, sub in found if sub is not None and not getattr(sub, "hidden", False)]


def command_markdown(command: Any, name: str, parent: Any | None = None, level: int = 2) -> str:
    """Markdown reference of one command: heading, help text, usage line, parameter table.

    Parameters
    ----------
    command : click.Command
        The command, as built by ``typer.main.get_command``. The subcommands of a group follow,
        one heading level deeper.
    name : str
        The name the command is invoked by.
    parent : click.Context or None
        The context of the parent command (``None`` for the program itself).
    level : int
        Heading level of the command's heading (1-6).

    Returns
    -------
    str
        The Markdown text, ending with a newline.
    """
    ctx = _context(command, name, parent)
    lines = _section(command, ctx, level, with_help=False)
    for sub_name, sub in _subcommands(command, ctx):
        lines.append(command_markdown(sub, sub_name, ctx, min(level + 1, 6)))
    return "\n".join(lines).rstrip("\n") + "\n"


def cli_markdown(app: Any | None = None, name: str = "pidlab", level: int = 2) -> str:
    """Markdown reference of a whole typer application.

    Parameters
    ----------
    app : typer.Typer or None
        The application; ``None`` means pidlab's own command line (``pidlab.cli.main.app``).
    name : str
        The program name shown in headings and usage lines.
    level : int
        Heading level of the program's section and of each command's section (1-6).

    Returns
    -------
    str
        The Markdown text: a section for the program itself (its global options, ``--help``
        included), then one section per command in the order ``pidlab --help`` lists them.
    """
    import typer

    if app is None:
        from pidlab.cli.main import app as pidlab_app

        app = pidlab_app
    root = typer.main.get_command(app)
    ctx = _context(root, name, None)
    lines = _section(root, ctx, level, with_help=True)
    for sub_name, sub in _subcommands(root, ctx):
        lines.append(command_markdown(sub, sub_name, ctx, level))
    return "\n".join(lines).rstrip("\n") + "\n"
