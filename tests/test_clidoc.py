"""The generated CLI reference covers the real command line: every command, every option."""

from __future__ import annotations

import re
from pathlib import Path

import typer

from pidlab.cli import app
from pidlab.cli.clidoc import cli_markdown

ROOT = Path(__file__).resolve().parent.parent


def _commands() -> dict[str, object]:
    group = typer.main.get_command(app)
    return dict(group.commands)  # type: ignore[attr-defined]


def test_every_command_has_a_section_with_its_help_and_usage() -> None:
    text = cli_markdown()
    commands = _commands()
    assert {"linearize", "tune", "analyze", "roa", "bounds", "train", "experiment"} <= set(commands)
    for name, command in commands.items():
        assert f"## `pidlab {name}`\n" in text
        assert f"```text\npidlab {name} [OPTIONS]" in text
        first_line = (command.help or "").strip().splitlines()[0]  # type: ignore[attr-defined]
        assert first_line.split(":")[0] in text


def test_every_option_of_train_is_in_its_table() -> None:
    text = cli_markdown()
    section = text.split("## `pidlab train`", 1)[1].split("\n## ", 1)[0]
    command = _commands()["train"]
    options = [p for p in command.params if p.param_type_name == "option"]  # type: ignore[attr-defined]
    assert {o.opts[0] for o in options} >= {"--coach", "--recipe", "--algo", "--steps", "--seed"}
    for option in options:
        for spelling in [*option.opts, *option.secondary_opts]:
            assert re.search(rf"^\| .*`{re.escape(spelling)}`.* \|$", section, re.MULTILINE), spelling
        if option.help:
            assert option.help.split("(")[0].strip() in section
    # The argument, its default, a flag pair and a metavar.
    assert "| `ENV` | `str` | *required* |" in section
    assert "| `--progress` / `--no-progress` | flag | `--progress` |" in section
    assert "| `--coach` | `SPEC|none` |" in section


def test_every_option_of_every_command_appears() -> None:
    text = cli_markdown()
    sections = dict(re.findall(r"^## `pidlab (\w[\w-]*)`\n(.*?)(?=^## |\Z)", text, re.MULTILINE | re.DOTALL))
    for name, command in _commands().items():
        for param in command.params:  # type: ignore[attr-defined]
            if param.param_type_name == "option":
                assert f"`{param.opts[0]}`" in sections[name], (name, param.opts)
            else:
                assert f"`{param.metavar or param.name.upper()}`" in sections[name], (name, param.name)
    # Global options, the help option included once (not in every command's table).
    assert "`--version`" in text
    assert text.count("`--help`") == 1


def test_defaults_are_shown() -> None:
    text = cli_markdown()
    assert "| `--samples` | `int` | `1000` |" in text
    assert "| `--conditions` | `NAME[,NAME...]` | `none,paper,pidlab,pidlab-fading` |" in text


def test_reference_page_has_the_marker_the_hook_replaces() -> None:
    import importlib.util

    spec = importlib.util.spec_from_file_location("cli_reference", ROOT / "docs/hooks/cli_reference.py")
    assert spec is not None and spec.loader is not None
    hook = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(hook)
    page_text = (ROOT / "docs" / hook.PAGE).read_text()
    assert hook.MARKER in page_text

    class _File:
        src_uri = hook.PAGE

    class _Page:
        file = _File()

    out = hook.on_page_markdown(page_text, _Page(), None, None)
    assert hook.MARKER not in out
    assert "## `pidlab train`" in out
