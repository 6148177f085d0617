"""``pidlab tune`` and ``pidlab analyze`` as a user runs them."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from pidlab.controller.spec import load_spec

TUNING = Path(__file__).resolve().parents[1] / "tuning"
PIDLAB = [sys.executable, "-m", "pidlab"]


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*PIDLAB, *args], capture_output=True, text=True, timeout=300)


def test_analyze_paper_coach_says_unstable_and_writes_plots(tmp_path):
    res = run(
        "analyze", str(TUNING / "InvertedPendulum-v5.paper.toml"), "--episodes", "3", "--plots", str(tmp_path)
    )
    assert res.returncode == 0, res.stderr
    assert "UNSTABLE" in res.stdout and "do not certify anything" in res.stdout
    assert "PM (deg)" in res.stdout and "GM (dB)" in res.stdout and "(rad/s)" in res.stdout
    assert "3x hinge_pos outside [-0.2, 0.2]" in res.stdout
    assert {p.name for p in tmp_path.iterdir()} == {
        "bode_slide.png",
        "nyquist_slide.png",
        "poles.png",
        "responses.png",
    }


def test_tune_writes_a_spec_that_analyzes_stable(tmp_path):
    out = tmp_path / "ip.toml"
    res = run(
        "tune", "InvertedPendulum-v5", "--auto", "--bandwidth", "12", "--phase-margin", "50", "-o", str(out)
    )
    assert res.returncode == 0, res.stderr
    assert "asked 12, achieved" in res.stdout
    spec = load_spec(out)
    assert spec.provenance["asked_bandwidth_rad_s"] == 12.0
    res = run("analyze", str(out), "--episodes", "2")
    assert res.returncode == 0 and "STABLE" in res.stdout and "2x time limit" in res.stdout


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["tune", "InvertedPendulum-v5"], "exactly one of --auto"),
        (["tune", "InvertedPendulum-v5", "--auto", "--preset", "strong"], "expected robust, weak, room or balance"),
        (["tune", "Ant-v5", "--auto"], "no tuning template for Ant-v5"),
        (["tune", "InvertedPendulum-v5", "--auto", "--bandwidth", "-3"], "positive frequency"),
        (["tune", "InvertedPendulum-v5", "--auto", "--bandwidth", "1e20"],
         "at or above the Nyquist frequency of the coach's control period (pi / 0.04 s = 78.54 rad/s)"),
        # -o into read-only /proc: were the option not refused, nothing would be tuned or written
        (["tune", "InvertedPendulum-v5", "--auto", "--port", "7000", "-o", "/proc/no/ip.toml"],
         "--port: a setting of the tuner in the browser"),
        (["tune", "InvertedPendulum-v5", "--auto", "--preset", "room", "--bandwidth", "3", "-o", "/proc/no/ip.toml"],
         "--bandwidth: --preset room chooses the gains"),
        (["roa", str(TUNING / "InvertedPendulum-v5.paper.toml"), "--slice", "foo,bar"],
         "--slice: names the plots' two variables; expected --plots DIR"),
        (["analyze", "no/such/spec.toml"], "cannot read coach spec"),
        (
            ["analyze", str(TUNING / "InvertedPendulum-v5.paper.toml"), "--episodes", "-1"],
            "expected 0 or more",
        ),
    ],
)
def test_bad_input_exit_2(args, message):
    res = run(*args)
    assert res.returncode == 2, res.stdout + res.stderr
    assert "Traceback" not in res.stderr
    assert message in res.stderr and len(res.stderr.strip().splitlines()) == 1


def test_malformed_spec_file_exit_2(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text((TUNING / "InvertedPendulum-v5.paper.toml").read_text().replace('"hinge_pos"', '"angle"'))
    res = run("analyze", str(bad))
    assert res.returncode == 2
    assert "'angle' is not an observation variable of InvertedPendulum-v5; valid names:" in res.stderr


def _tree(root: Path) -> dict[str, tuple[bytes, int]]:
    return {
        str(p.relative_to(root)): (p.read_bytes() if p.is_file() else b"<dir>", p.stat().st_mode)
        for p in sorted(root.rglob("*"))
    }


def test_read_only_places_are_refused_before_the_work_and_left_alone(tmp_path, monkeypatch):
    """Read-only files and folders (no write bit: refused even for root, who could write them)."""
    from tests.helpers import cli_in_process

    monkeypatch.chdir(tmp_path)
    spec = tmp_path / "spec.toml"
    spec.write_bytes((TUNING / "InvertedPendulum-v5.pidlab-robust.toml").read_bytes())
    spec.chmod(0o444)
    (tmp_path / "ro").mkdir()
    (tmp_path / "ro").chmod(0o555)
    before = _tree(tmp_path)
    cases = [
        (["bounds", str(spec), "--write", "--samples", "10"], "--write '"),
        (["tune", "InvertedPendulum-v5", "--auto", "-o", str(spec)], "the file is read-only"),
        (["tune", "InvertedPendulum-v5", "--auto", "-o", "ro/ip.toml"], "the folder ro is read-only"),
        (["analyze", str(spec), "--plots", "ro/plots"], "--plots 'ro/plots': cannot write there"),
        (["roa", str(spec), "--plots", "ro"], "--plots 'ro'"),
        (["train", "InvertedPendulum-v5", "--coach", "none", "--run-dir", "ro/run"], "--run-dir 'ro/run'"),
    ]
    try:
        for args, words in cases:
            code, stderr = cli_in_process(*args)
            assert code == 2 and len(stderr.splitlines()) == 1 and words in stderr, (args, stderr)
        assert _tree(tmp_path) == before  # the spec keeps its bytes and its mode 0444
    finally:
        (tmp_path / "ro").chmod(0o755)


def test_atomic_writes_clean_up_and_keep_the_mode(tmp_path, monkeypatch):
    import errno
    import os

    from pidlab.errors import OutputError
    from pidlab.files import atomic_write_text

    target = tmp_path / "a.toml"
    target.write_text("old")
    target.chmod(0o600)
    atomic_write_text(target, "new")
    assert target.read_text() == "new" and (target.stat().st_mode & 0o777) == 0o600

    def full(src, dst):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "replace", full)
    with pytest.raises(OutputError, match="No space left on device") as err:
        atomic_write_text(target, "newer")
    assert isinstance(err.value, OSError)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.toml"] and target.read_text() == "new"
    monkeypatch.undo()
    with pytest.raises(OutputError, match="is a folder"):
        atomic_write_text(tmp_path, "x")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.toml"]


def test_permissions_of_another_user_are_refused(tmp_path, monkeypatch):
    """What a non-root user meets (os.access says no), without running as one."""
    import os

    from pidlab.errors import OutputError
    from pidlab.files import atomic_write_text, check_output_folder

    real_access = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: False if mode & os.W_OK else real_access(p, mode))
    (tmp_path / "a.toml").write_text("old")
    with pytest.raises(OutputError, match="the file is read-only"):
        atomic_write_text(tmp_path / "a.toml", "new")
    with pytest.raises(OutputError, match=r"^param='.*/x/y': cannot write there: the folder .* is read-only$"):
        check_output_folder(tmp_path / "x" / "y", "param")
    assert (tmp_path / "a.toml").read_text() == "old" and not (tmp_path / "x").exists()


def test_analyze_shows_progress_and_sigterm_exits_130(tmp_path):
    """A long analyze shows a bar (--progress); SIGTERM stops it like Ctrl-C: one line, exit 130."""
    import os
    import signal

    proc = subprocess.Popen(
        [*PIDLAB, "analyze", str(TUNING / "InvertedPendulum-v5.pidlab-robust.toml"), "--episodes", "10000",
         "--progress"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
    )  # fmt: skip
    assert proc.stderr is not None
    seen = b""
    while b"coach-alone episodes" not in seen:  # the bar is drawn: the episodes are running
        chunk = os.read(proc.stderr.fileno(), 4096)
        assert chunk, seen
        seen += chunk
    proc.send_signal(signal.SIGTERM)
    text = (seen + proc.stderr.read()).decode(errors="replace")
    assert proc.wait(timeout=60) == 130
    assert text.rstrip().endswith("pidlab: interrupted") and "Traceback" not in text, text
