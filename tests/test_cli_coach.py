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
        (["tune", "InvertedPendulum-v5", "--auto", "--preset", "strong"], "expected robust or weak"),
        (["tune", "Ant-v5", "--auto"], "no tuning template for Ant-v5"),
        (["tune", "InvertedPendulum-v5", "--auto", "--bandwidth", "-3"], "positive frequency"),
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
