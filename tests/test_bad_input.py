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

from tests.helpers import DATA, TUNING, cli_in_process

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


SPECIAL = {
    "analyze": ["analyze", "{p}"],
    "linearize": ["linearize", "{p}"],
    "train": ["train", "InvertedPendulum-v5", "--coach", "none", "--recipe", "{p}", "--steps", "100",
              "--run-dir", "{tmp}/run"],
    "experiment": ["experiment", "--conditions-file", "{p}", "--envs", "InvertedPendulum-v5", "--seeds", "1",
                   "--steps", "100", "--out", "{tmp}/sweep"],
}  # fmt: skip
"""Commands that read a file a user names, with ``{p}`` for it: a spec, a model, a recipe, conditions."""


def _special_file(kind: str, folder: Path, suffix: str) -> Path:
    """A path whose read would block (a named pipe), read a device, or read more than a file may hold."""
    import os

    path = folder / f"{kind}{suffix}"
    if kind == "pipe":
        os.mkfifo(path)
    elif kind == "device":
        path.symlink_to("/dev/null")  # reads as empty: without the check the case fails, it does not hang
    else:
        with open(path, "wb") as fh:
            fh.truncate(2**30 + 1 if suffix == ".xml" else 64 * 2**20 + 1)  # sparse: no disk used
    return path


@pytest.mark.parametrize("kind, expect", [("pipe", "it is a named pipe; expected a regular file"),
                                          ("device", "it is a device; expected a regular file"),
                                          ("huge", "bytes; expected at most")])  # fmt: skip
@pytest.mark.parametrize("verb", sorted(SPECIAL))
def test_a_pipe_a_device_or_a_huge_file_is_refused_before_it_is_read(
    verb: str, kind: str, expect: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A named pipe would block the command forever, ``/dev/zero`` fill the memory, a sparse file of
    terabytes too: each is refused in one line, without a read. Should a command open the pipe, a
    writer opened after 20 s ends its wait, so this test fails instead of hanging."""
    import os
    import threading

    monkeypatch.chdir(tmp_path)
    path = _special_file(kind, tmp_path, ".xml" if verb == "linearize" else ".toml")
    done = threading.Event()

    def unblock() -> None:
        if not done.wait(20) and kind == "pipe":
            os.close(os.open(path, os.O_WRONLY))

    guard = threading.Thread(target=unblock, daemon=True)
    guard.start()
    args = [a.replace("{p}", str(path)).replace("{tmp}", str(tmp_path)) for a in SPECIAL[verb]]
    try:
        code, stderr = cli_in_process(*args)
    finally:
        done.set()
    lines = stderr.strip().splitlines()
    assert code == 2 and len(lines) == 1, stderr
    assert str(path) in lines[0] and expect in lines[0], lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]


@pytest.mark.parametrize("kind, expect", [("pipe", "is a named pipe, not a file; pidlab writes regular files only"),
                                          ("device", "is a device, not a file; pidlab writes regular files only")])  # fmt: skip
def test_an_output_that_is_a_pipe_or_a_device_is_never_replaced(
    kind: str, expect: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``-o /dev/null --force`` run as root replaced the device with a regular file (the write is a
    rename over the path). A pipe or a device (here a link to /dev/null: the link would be replaced,
    not the device, should the check fail) is refused before any work, and left as it was."""
    from pidlab.errors import OutputError
    from pidlab.files import atomic_write_text

    monkeypatch.chdir(tmp_path)
    path = _special_file(kind, tmp_path, ".toml")
    before = path.lstat()
    spec = str(TUNING / "InvertedPendulum-v5.pidlab-rescue.toml")
    code, stderr = cli_in_process("rescue-classifier", spec, "--domain", "hinge_pos=0.2", "-o", str(path),
                                  "--force", "--workers", "1")  # fmt: skip
    lines = stderr.strip().splitlines()
    assert code == 2 and len(lines) == 1 and expect in lines[0], stderr
    with pytest.raises(OutputError, match=expect):
        atomic_write_text(path, "x")
    after = path.lstat()
    assert (after.st_mode, after.st_ino) == (before.st_mode, before.st_ino)
    assert sorted(p.name for p in tmp_path.iterdir()) == [path.name]
