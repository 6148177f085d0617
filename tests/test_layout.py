"""The package's architecture, checked on its source: stage order, errors in one place, short functions.

These hold the design card (shared/DESIGN.md) true as the code grows: a module may import from its
own stage and from earlier ones, never from a later one.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from tests.helpers import ROOT

PACKAGE = ROOT / "pidlab"
STAGES = (
    ("errors", "checks", "files", "provenance", "data", "orphans", "parallel", "interrupts", "lookup", "__init__"),
    ("plant", "project"),
    ("linear",),
    ("controller",),
    ("region",),
    ("rl",),
    ("experiment",),
    ("report",),
    ("pipeline",),
    ("cli", "app", "__main__"),
)
MAX_LINES = 80
"""The longest a function may be, docstring included."""


def _modules() -> list[Path]:
    return sorted(PACKAGE.rglob("*.py"))


def _stage(parts: tuple[str, ...]) -> int:
    head = parts[0].removesuffix(".py")
    for rank, names in enumerate(STAGES):
        if head in names:
            return rank
    raise AssertionError(f"pidlab/{'/'.join(parts)} belongs to no stage; add it to STAGES")


def _imports(tree: ast.AST) -> list[tuple[str, int]]:
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("pidlab."):
            found.append((node.module, node.lineno))
        elif isinstance(node, ast.Import):
            found += [(a.name, node.lineno) for a in node.names if a.name.startswith("pidlab.")]
    return found


def test_no_module_imports_from_a_later_stage() -> None:
    wrong = []
    for path in _modules():
        rel = path.relative_to(PACKAGE).parts
        if rel == ("__init__.py",):
            continue  # the top level re-exports every stage, lazily
        mine = _stage(rel)
        for module, line in _imports(ast.parse(path.read_text())):
            theirs = _stage(tuple(module.split(".")[1:]))
            if theirs > mine:
                wrong.append(f"pidlab/{'/'.join(rel)}:{line} imports {module}")
    assert not wrong, "\n".join(wrong)


def test_every_exception_class_lives_in_errors_py() -> None:
    elsewhere = []
    for path in _modules():
        if path.name == "errors.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef) and any(
                isinstance(b, ast.Name) and (b.id.endswith(("Error", "Exception")) or b.id == "PidlabError")
                for b in node.bases
            ):
                elsewhere.append(f"{path.relative_to(ROOT)}: class {node.name}")
    assert not elsewhere, "\n".join(elsewhere)


def test_every_error_class_has_a_one_line_docstring() -> None:
    tree = ast.parse((PACKAGE / "errors.py").read_text())
    for node in tree.body:
        if isinstance(node, ast.ClassDef):
            doc = ast.get_docstring(node)
            assert doc, node.name
            assert "\n" not in doc.split("\n\n")[0], f"{node.name}: the summary is more than one line"


@pytest.mark.parametrize("path", _modules(), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_functions_are_short(path: Path) -> None:
    long = [
        f"{node.name}: {node.end_lineno - node.lineno + 1} lines"
        for node in ast.walk(ast.parse(path.read_text()))
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
        and node.end_lineno is not None
        and node.end_lineno - node.lineno + 1 > MAX_LINES
    ]
    assert not long, long


def test_no_assert_statements_in_the_package() -> None:
    # an assert is no check: python -O removes it, and a user who reaches one gets a traceback
    found = [
        f"{path.relative_to(ROOT)}:{node.lineno}"
        for path in _modules()
        for node in ast.walk(ast.parse(path.read_text()))
        if isinstance(node, ast.Assert)
    ]
    assert not found, found


def test_nothing_sets_the_matplotlib_backend_and_data_is_found_in_one_place() -> None:
    for path in _modules():
        text = path.read_text()
        assert "matplotlib.use(" not in text, path
        if path.name not in ("data.py", "provenance.py"):
            assert "__file__).resolve().parent" not in text, f"{path}: locate data through pidlab.data"
