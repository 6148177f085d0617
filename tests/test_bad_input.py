"""Bad input, by family: one line on stderr, exit code 2, no traceback, and nothing changed.

The corpus is ``tests/data/bad/``: one TOML file of cases per family (``files.toml``, ...), and the
bad files themselves in ``files/``. A case is::

    [[case]]
    id = "spec-utf16"                                   # unique over the corpus
    args = ["analyze", "{bad}/spec-utf16.toml"]         # the pidlab command line
    expect = "spec-utf16.toml"                          # a substring of the one error line

``{bad}`` is a scratch copy of ``files/`` and ``{tmp}`` an empty scratch folder (the working
directory). The test snapshots the whole scratch tree (bytes and modes) before and after: a case
fails if the command wrote, removed or changed anything there.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path
from typing import Any

import pytest

from tests.helpers import DATA, cli_in_process

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

CORPUS = DATA / "bad"


def _cases() -> list[Any]:
    cases = []
    for path in sorted(CORPUS.glob("*.toml")):
        for case in tomllib.loads(path.read_text(encoding="utf-8"))["case"]:
            cases.append(pytest.param(case, id=f"{path.stem}/{case['id']}"))
    return cases


def _snapshot(root: Path) -> dict[str, tuple[bytes, int]]:
    return {
        str(p.relative_to(root)): (p.read_bytes() if p.is_file() else b"<dir>", p.stat().st_mode)
        for p in sorted(root.rglob("*"))
    }


def test_case_ids_are_unique() -> None:
    ids = [c.values[0]["id"] for c in _cases()]
    assert len(ids) == len(set(ids))


@pytest.mark.parametrize("case", _cases())
def test_bad_input_is_one_line_exit_2_and_changes_nothing(
    case: dict[str, Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    bad, work = tmp_path / "bad", tmp_path / "work"
    shutil.copytree(CORPUS / "files", bad)
    work.mkdir()
    monkeypatch.chdir(work)
    args = [a.replace("{bad}", str(bad)).replace("{tmp}", str(work)) for a in case["args"]]
    before = _snapshot(tmp_path)
    code, stderr = cli_in_process(*args)
    lines = stderr.strip().splitlines()
    assert code == 2, stderr
    assert len(lines) == 1 and lines[0].startswith("pidlab: error: "), stderr
    assert case["expect"] in lines[0], lines[0]
    assert _snapshot(tmp_path) == before, "the command changed the scratch folder"
