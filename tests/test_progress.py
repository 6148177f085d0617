"""A sweep's progress in env steps, read from its runs' logs (hand-made run folders, no training)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from pidlab.errors import RunDirError
from pidlab.experiment.progress import (
    TAIL_BYTES,
    RunProgress,
    logged_env_steps,
    run_progress,
    steps_done,
)
from pidlab.experiment.sweep import RunOutcome, RunTask, _Tally
from pidlab.provenance import hold_lock, lock_holder
from pidlab.report.console import status_lines
from pidlab.rl.rundir import EPISODE_COLUMNS, LEGACY_EPISODE_COLUMNS
from tests.helpers import cli_in_process


def _row(steps: int, width: int = len(EPISODE_COLUMNS)) -> str:
    return ",".join([str(steps // 10), str(steps)] + ["0"] * (width - 2))


def _log(run_dir: Path, steps: list[int], columns: tuple[str, ...] = EPISODE_COLUMNS, tail: str = "") -> Path:
    run_dir.mkdir(parents=True, exist_ok=True)
    rows = "".join(_row(s, len(columns)) + "\n" for s in steps)
    (run_dir / "episodes.csv").write_text(",".join(columns) + "\n" + rows + tail)
    return run_dir


def test_no_log_or_no_row_is_no_progress(tmp_path):
    assert logged_env_steps(tmp_path / "missing") == 0
    assert logged_env_steps(_log(tmp_path / "empty", [])) == 0
    (tmp_path / "blank").mkdir()
    (tmp_path / "blank" / "episodes.csv").write_text("")
    assert logged_env_steps(tmp_path / "blank") == 0
    (tmp_path / "folder" / "episodes.csv").mkdir(parents=True)
    assert logged_env_steps(tmp_path / "folder") == 0
    (tmp_path / "pipe").mkdir()
    os.mkfifo(tmp_path / "pipe" / "episodes.csv")  # opening it would wait for a writer
    assert logged_env_steps(tmp_path / "pipe") == 0
    (tmp_path / "noise").mkdir()
    (tmp_path / "noise" / "episodes.csv").write_bytes(b"x" * (100 * TAIL_BYTES))  # no newline at all
    assert logged_env_steps(tmp_path / "noise") == 0


def test_the_last_complete_row_counts_and_a_row_being_written_does_not(tmp_path):
    assert logged_env_steps(_log(tmp_path / "a", [13, 40, 77])) == 77
    assert logged_env_steps(_log(tmp_path / "b", [13, 40], tail="4,45,0")) == 40
    assert logged_env_steps(_log(tmp_path / "c", [13, 40, 77], columns=LEGACY_EPISODE_COLUMNS)) == 77


def test_a_long_log_is_read_from_its_end(tmp_path):
    steps = list(range(1, 5 * TAIL_BYTES))
    run = _log(tmp_path / "long", steps, tail=_row(10**6)[:7])
    assert (run / "episodes.csv").stat().st_size > 10 * TAIL_BYTES
    assert logged_env_steps(run) == steps[-1]


@pytest.mark.parametrize("last", ["4,abc,0", "4,-5," + "0," * (len(EPISODE_COLUMNS) - 3) + "0", "4,50"])
def test_a_damaged_last_row_is_no_progress(tmp_path, last):
    assert logged_env_steps(_log(tmp_path / "run", [13], tail=last + "\n")) == 0


def test_a_finished_run_counts_its_budget_and_a_log_never_counts_past_it(tmp_path):
    run = _log(tmp_path / "run", [50, 120])
    assert steps_done(run, 100) == 100
    assert steps_done(run, 1000) == 120
    (run / "summary.json").write_text(json.dumps({"completed": True, "env_steps": 1000}))
    assert steps_done(run, 1000) == 1000
    (run / "summary.json").write_text("{damaged")
    assert steps_done(run, 1000) == 120


def _task(tmp_path: Path, seed: int, steps: int) -> RunTask:
    run_dir = tmp_path / "runs" / "Env-v0" / "none" / f"seed-{seed}"
    return RunTask("Env-v0", "none", seed, str(run_dir), {"steps": steps}, None, None, "digest")


def test_the_tally_counts_finished_copied_and_running_runs_in_env_steps(tmp_path, capsys):
    tasks = [_task(tmp_path, s, 1000) for s in range(4)]
    _finished, copied, running, queued = tasks
    _log(Path(running.run_dir), [100, 300])
    tally = _Tally(tasks, [running, queued], progress_bar=False, copied=[Path(copied.run_dir)])
    assert tally.total == 4000
    assert tally.steps == {(t.env_id, t.condition, t.seed): s for t, s in zip(tasks, [1000, 1000, 300, 0], strict=True)}

    _log(Path(running.run_dir), [100, 300, 650])
    tally.poll()
    assert sum(tally.steps.values()) == 2650

    _log(Path(running.run_dir), [100])  # a resume rewound its log to a checkpoint: no step back
    tally.poll()
    assert sum(tally.steps.values()) == 2650

    tally(RunOutcome("Env-v0", "none", 1, "reused"))
    tally(RunOutcome("Env-v0", "none", 2, "done"))
    assert sum(tally.steps.values()) == 3000
    tally(RunOutcome("Env-v0", "none", 3, "stopped"))
    assert sum(tally.steps.values()) == 3000
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines == ["pidlab: run Env-v0/none/seed-2 done (3 of 4 runs finished; 3,000 of 4,000 env steps)"]
    assert [o.status for o in tally.ordered(tasks)] == ["skipped", "reused", "done", "stopped"]


def test_a_failed_run_is_one_line_on_stderr(tmp_path, capsys):
    task = _task(tmp_path, 0, 1000)
    tally = _Tally([task], [task], progress_bar=False)
    tally(RunOutcome("Env-v0", "none", 0, "failed", error="RunDirError: damaged"))
    assert capsys.readouterr().err.strip() == "pidlab: run Env-v0/none/seed-0 failed: RunDirError: damaged"
    assert tally.steps[("Env-v0", "none", 0)] == 0


def _checkpoint(run_dir: Path, env_steps: int, **override: object) -> None:
    folder = run_dir / "checkpoints" / f"{env_steps:012d}"
    folder.mkdir(parents=True)
    state = {"env_steps": env_steps, "agent_steps": env_steps, "coach_steps": 0, "episodes": 3,
             "evaluations": 1, "num_timesteps": env_steps, **override}  # fmt: skip
    (folder / "state.json").write_text(json.dumps(state))


def test_a_run_is_not_started_under_way_finished_or_damaged(tmp_path):
    assert run_progress(tmp_path / "nothing", 1000) == RunProgress("not started", 0, 0, False)
    run = _log(tmp_path / "run", [40, 130])
    assert run_progress(run, 1000) == RunProgress("under way", 0, 130, False)
    _checkpoint(run, 100)
    assert run_progress(run, 1000) == RunProgress("under way", 100, 130, False)
    (run / "summary.json").write_text(json.dumps({"completed": True, "env_steps": 1000}))
    assert run_progress(run, 1000) == RunProgress("finished", 1000, 1000, False)

    cut = _log(tmp_path / "cut", [40])
    _checkpoint(cut, 30, agent_steps=7)  # its counters disagree
    found = run_progress(cut, 1000)
    assert (found.state, found.checkpointed, found.logged) == ("damaged", 0, 40)
    assert "env_steps is not agent_steps + coach_steps" in found.problem
    _checkpoint(cut, 20)  # an older one that reads: a resume falls back to it
    found = run_progress(cut, 1000)
    assert (found.state, found.checkpointed) == ("damaged", 20)
    assert "env_steps is not agent_steps + coach_steps" in found.problem
    (run / "summary.json").write_text("{cut")
    found = run_progress(run, 1000)
    assert (found.state, found.checkpointed, found.logged) == ("damaged", 100, 130)
    assert "summary.json" in found.problem


def test_a_run_whose_lock_is_held_is_training_now(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    assert lock_holder(run) is None
    with hold_lock(run, RunDirError):
        assert lock_holder(run) == os.getpid()
        assert run_progress(run, 1000) == RunProgress("under way", 0, 0, True)
    assert lock_holder(run) is None
    assert run_progress(run, 1000).state == "not started"


def test_the_status_lines_hand_computed():
    rows = [
        ("Env-v0", "none", 0, 1000, RunProgress("finished", 1000, 1000, False)),
        ("Env-v0", "none", 1, 1000, RunProgress("under way", 400, 650, True)),
        ("Env-v0", "coached", 0, 1000, RunProgress("not started", 0, 0, False)),
        ("Env-v0", "coached", 1, 1000, RunProgress("damaged", 0, 20, False, "state.json: damaged")),
    ]
    assert status_lines(rows) == [
        "Env-v0 none     2 runs: 1 finished, 1 under way",
        "Env-v0 coached  2 runs: 1 not started, 1 damaged",
        "  Env-v0/none/seed-1: checkpoint at 400 of 1,000 env steps, log at 650; training now",
        "  Env-v0/coached/seed-1: checkpoint at 0 of 1,000 env steps, log at 20; damaged: state.json: damaged",
        "runs: 1 finished, 1 under way, 1 not started, 1 damaged (of 4); 1,400 of 4,000 env steps checkpointed "
        "(35.0 %)",
    ]


@pytest.mark.parametrize(
    ("extra", "line"),
    [
        (["--report-only"], "--status with --report-only: the status writes no report (drop one of them)"),
        (["--workers", "0"], "--workers 0: expected an integer in [1, 256]"),
        (["--address", "127.0.0.1:1"], "--address '127.0.0.1:1': only with the ray backend"),
        (["--backend", "mpi"], "--backend 'mpi': expected one of process, ray"),
    ],
)
def test_the_status_checks_the_options_of_its_command_in_one_line(tmp_path, extra, line):
    out = tmp_path / "exp"
    args = ["experiment", "--envs", "InvertedPendulum-v5", "--conditions", "none", "--seeds", "2", "--out", str(out)]
    code, stderr = cli_in_process(*args, "--status", *extra)
    assert (code, stderr.strip()) == (2, f"pidlab: error: {line}")
    assert not out.exists()


def test_the_status_of_an_experiment_not_started_creates_nothing(tmp_path):
    from typer.testing import CliRunner

    from pidlab.cli import app

    out = tmp_path / "exp"
    args = ["experiment", "--envs", "InvertedPendulum-v5", "--conditions", "none", "--seeds", "2", "--out", str(out),
            "--steps", "5000", "--status"]  # fmt: skip
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert result.stdout.splitlines() == [
        f"experiment {out.resolve()} (not started: no experiment.json)",
        "InvertedPendulum-v5 none  2 runs: 2 not started",
        "runs: 0 finished, 0 under way, 2 not started, 0 damaged (of 2); 0 of 10,000 env steps checkpointed (0.0 %)",
    ]
    assert not out.exists()
