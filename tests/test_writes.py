"""Writing coach specs and run files: one rule for every writer, and a full disk.

Every command that writes a spec takes its lock while it works on an existing file, keeps every
table it does not own, and refuses to replace a file unless ``--force`` is given; a refusal
changes nothing. A full disk while training is one line, and the run resumes afterwards.
"""

from __future__ import annotations

import errno
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pidlab.controller.spec import load_spec, writing_spec
from pidlab.errors import SpecError
from pidlab.rl.rundir import checkpoint_folders
from tests.helpers import ROOT, cli_in_process
from tests.test_recovery import HOLD, assert_logs_consistent, snapshot, tiny_recipe

IP = "InvertedPendulum-v5"


def _one_line(code: int, stderr: str) -> str:
    lines = stderr.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("pidlab: error: "), stderr
    return lines[0]


def test_bounds_write_keeps_the_rescue_region_and_the_takeover_choice(tmp_path: Path) -> None:
    spec_file = Path(shutil.copy(ROOT / "tuning" / f"{IP}.pidlab-rescue.toml", tmp_path / "spec.toml"))
    before = load_spec(spec_file)
    assert before.bounds is not None and before.bounds["takeover"] == "rescue"
    code, stderr = cli_in_process("bounds", str(spec_file), "--write", "--samples", "20", "--workers", "1")
    assert code == 0, stderr
    after = load_spec(spec_file)
    assert after.bounds is not None
    assert after.bounds["rescue"] == before.bounds["rescue"]
    assert after.bounds["takeover"] == "rescue"
    assert after.bounds["provenance"]["samples"] == 20  # the bounds themselves were rewritten


def test_bounds_write_drops_a_takeover_that_names_a_region_it_no_longer_has() -> None:
    from dataclasses import replace

    from pidlab.region.bounds import with_bounds

    spec = load_spec(ROOT / "tuning" / f"{IP}.pidlab-robust.toml")
    assert spec.bounds is not None and "box" in spec.bounds
    old = replace(spec, bounds={**spec.bounds, "takeover": "box", "extra": {"kept": True}})

    from pidlab.region.bounds import CriticalBounds

    e = spec.bounds["ellipsoid"]
    no_box = CriticalBounds(  # what derive_bounds gives without box variables
        env_id=IP, spec_name=spec.name, method=spec.bounds["method"], variables=tuple(e["variables"]),
        center=np.array(e["center"]), shape=np.array(e["shape"]), level=e["level"], rho=e["rho"], box={},
        one_step_check=(0, 0), provenance=dict(spec.bounds["provenance"]),
    )  # fmt: skip
    table = with_bounds(old, no_box).bounds
    assert table is not None and "box" not in table and table["extra"] == {"kept": True}
    assert "takeover" not in table  # it named the box, which is gone: the default applies
    kept = with_bounds(replace(spec, bounds={**spec.bounds, "takeover": "ellipsoid"}), no_box)
    assert kept.bounds is not None and kept.bounds["takeover"] == "ellipsoid"


@pytest.mark.parametrize("target", ["copy", "shipped"])
def test_tune_refuses_to_overwrite_a_spec_without_force(tmp_path: Path, target: str) -> None:
    shipped = ROOT / "tuning" / f"{IP}.paper.toml"
    out = shipped if target == "shipped" else Path(shutil.copy(shipped, tmp_path / "mine.toml"))
    text = out.read_bytes()
    code, stderr = cli_in_process("tune", IP, "--auto", "-o", str(out))
    line = _one_line(code, stderr)
    assert "--output" in line and "the file exists" in line and "--force" in line, line
    assert out.read_bytes() == text
    assert not list(out.parent.glob(f".{out.name}*"))  # no temporary file, no lock file


def test_tune_force_replaces_the_spec_and_a_new_file_is_created(tmp_path: Path) -> None:
    out = Path(shutil.copy(ROOT / "tuning" / f"{IP}.paper.toml", tmp_path / "mine.toml"))
    code, stderr = cli_in_process("tune", IP, "--auto", "--force", "-o", str(out), "--workers", "1")
    assert code == 0, stderr
    assert load_spec(out).name == "pidlab-robust"
    fresh = tmp_path / "fresh.toml"
    code, stderr = cli_in_process("tune", IP, "--auto", "-o", str(fresh), "--workers", "1")
    assert code == 0 and load_spec(fresh).name == "pidlab-robust", stderr


def test_tune_force_is_refused_while_another_command_holds_the_spec(tmp_path: Path) -> None:
    out = Path(shutil.copy(ROOT / "tuning" / f"{IP}.paper.toml", tmp_path / "mine.toml"))
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(out)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        before = snapshot(tmp_path)
        code, stderr = cli_in_process("tune", IP, "--auto", "--force", "-o", str(out))
        assert f"(pid {holder.pid})" in _one_line(code, stderr)
        assert snapshot(tmp_path) == before
    finally:
        holder.kill()
        holder.wait()


def test_a_file_that_appears_while_a_new_spec_is_made_is_not_replaced(tmp_path: Path) -> None:
    spec = load_spec(ROOT / "tuning" / f"{IP}.paper.toml")
    out = tmp_path / "new.toml"
    with pytest.raises(SpecError, match="another command created the file meanwhile"):
        with writing_spec(out, param="output") as write:
            out.write_text("# someone else's\n")
            write(spec)
    assert out.read_text() == "# someone else's\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["new.toml"]


def test_a_full_disk_while_training_is_one_line_and_the_run_resumes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import pidlab.rl.train as train_module

    real = train_module.save_agent
    calls = {"n": 0}

    def fill_up(folder: Path, *args, **kwargs):  # type: ignore[no-untyped-def]
        calls["n"] += 1
        if calls["n"] == 2:  # the second checkpoint finds the disk full
            raise OSError(errno.ENOSPC, "No space left on device", str(folder / "model.zip"))
        return real(folder, *args, **kwargs)

    monkeypatch.setattr(train_module, "save_agent", fill_up)
    run = tmp_path / "run"
    args = ("train", IP, "--coach", "none", "--recipe", str(tiny_recipe(tmp_path)), "--run-dir", str(run))
    line = _one_line(*cli_in_process(*args, "--no-progress"))
    assert "no space left on device" in line and f"pidlab train {IP} --resume {run}" in line, line
    assert len(checkpoint_folders(run)) == 1  # the first checkpoint stays; the second was cut short
    monkeypatch.setattr(train_module, "save_agent", real)
    code, stderr = cli_in_process("train", IP, "--resume", str(run), "--no-progress")
    assert code == 0, stderr
    assert_logs_consistent(run)
