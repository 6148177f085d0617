"""Recovery: the one lock, check-then-write resumes, the checkpoint fallback, damaged run folders,
and a killed sweep whose workers stop with it.

One small run (uncoached PPO on InvertedPendulum-v5, a few hundred env steps, two checkpoints) is
trained once per module and copied for each test; the tests damage the copy and resume it.
Processes are real only where the behaviour needs them (the lock between two commands, SIGKILL).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import tomli_w

from pidlab.errors import PidlabError, RunDirError
from pidlab.provenance import LOCK_NAME, hold_lock, new_record, write_record
from pidlab.rl.recipe import load_recipe
from pidlab.rl.rundir import checkpoint_folders, read_csv_rows
from pidlab.rl.train import train
from tests.helpers import ROOT, cli_in_process

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

IP = "InvertedPendulum-v5"
PIDLAB = str(Path(sys.executable).with_name("pidlab"))
HOLD = """
import sys, time
from pidlab.errors import PidlabError
from pidlab.provenance import hold_lock
with hold_lock(sys.argv[1], PidlabError):
    print("held", flush=True)
    time.sleep(120)
"""


def tiny_recipe(folder: Path, steps: int = 600, every: int = 200) -> Path:
    """The shipped IP recipe with a budget of a few hundred env steps, checkpoints every ``every``."""
    data = tomllib.loads((ROOT / "coach" / f"{IP}.toml").read_text())
    data["steps"] = steps
    data["evaluation"] = {"every": every, "episodes": 1, "seed": 123}
    data["checkpoint"] = {"every": every}
    path = folder / f"tiny-{steps}-{every}.toml"
    path.write_text(tomli_w.dumps(data))
    return path


@pytest.fixture(scope="module")
def prepared(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A finished run of 600 env steps with its two checkpoints (about 400 and 600 env steps)."""
    folder = tmp_path_factory.mktemp("prepared")
    result = train(load_recipe(tiny_recipe(folder)), None, folder / "run", progress_bar=False)
    assert result.completed and len(checkpoint_folders(folder / "run")) == 2
    return folder / "run"


@pytest.fixture
def run(prepared: Path, tmp_path: Path) -> Path:
    """A copy of the prepared run, to damage."""
    return Path(shutil.copytree(prepared, tmp_path / "run"))


def snapshot(folder: Path) -> dict[str, tuple[bytes, int]]:
    return {
        str(p.relative_to(folder)): (p.read_bytes() if p.is_file() else b"<dir>", p.stat().st_mode)
        for p in sorted(folder.rglob("*"))
    }


def state(checkpoint: Path) -> dict[str, int]:
    return json.loads((checkpoint / "state.json").read_text())


def assert_logs_consistent(run: Path) -> None:
    """Episode ids 0..n-1, env steps never going back, one evaluation per env step."""
    eps = read_csv_rows(run / "episodes.csv")
    assert [int(r["episode"]) for r in eps] == list(range(len(eps)))
    steps = [int(r["env_steps_so_far"]) for r in eps]
    assert steps == sorted(steps)
    ev = [int(r["env_steps_so_far"]) for r in read_csv_rows(run / "evaluations.csv")]
    assert ev == sorted(set(ev))


def resume_cli(run: Path, *extra: str) -> tuple[int, list[str]]:
    code, stderr = cli_in_process("train", IP, "--resume", str(run), "--no-progress", *extra)
    return code, stderr.strip().splitlines()


# ---------------------------------------------------------------- the lock


def test_the_lock_is_reentrant_and_leaves_nothing(tmp_path):
    folder = tmp_path / "a" / "b"
    with hold_lock(folder, RunDirError) as lock:
        assert lock == folder.resolve() / LOCK_NAME and lock.read_text().strip() == str(os.getpid())
        with hold_lock(folder, RunDirError):  # the same process: no deadlock
            pass
        assert lock.exists()
    assert not (tmp_path / "a").exists()  # made for the lock, empty again: removed
    (tmp_path / "kept").mkdir()
    with pytest.raises(RunDirError, match="boom"), hold_lock(tmp_path / "kept", RunDirError):
        raise RunDirError("boom")
    assert list((tmp_path / "kept").iterdir()) == []


def test_a_lock_file_alone_leaves_a_folder_empty(tmp_path):
    """The folder guard ignores a lock file (a killed command's): the folder may hold a new run."""
    from pidlab.provenance import Refusals, check_folder

    (tmp_path / LOCK_NAME).write_text("12345\n")
    refusals = Refusals("file", "unreadable", "not ours", lambda old: "another")
    assert check_folder(tmp_path, "r.json", "s/1", None, refusals, PidlabError) is None
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(PidlabError, match="not ours"):
        check_folder(tmp_path, "r.json", "s/1", None, refusals, PidlabError)


def test_a_read_only_run_is_refused_before_any_write(run):
    (run / "summary.json").unlink()
    run.chmod(0o555)
    try:
        before = snapshot(run)
        code, lines = resume_cli(run, "--steps", "800")
        assert code == 2 and len(lines) == 1 and "read-only" in lines[0], lines
        assert snapshot(run) == before
    finally:
        run.chmod(0o755)


def test_a_held_lock_refuses_and_a_killed_holder_leaves_none(tmp_path):
    folder = tmp_path / "f"
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(folder)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        with pytest.raises(RunDirError) as info, hold_lock(folder, RunDirError):
            pass
        message = str(info.value)
        assert f"in use by another pidlab command (pid {holder.pid})" in message and "\n" not in message
        assert (folder / LOCK_NAME).exists()  # the holder's, untouched
        with (
            pytest.raises(PidlabError, match=r"^out=.*: in use"),
            hold_lock(folder, PidlabError, param="out"),
        ):
            pass
    finally:
        holder.kill()  # SIGKILL: the OS releases the lock; its file stays behind
        holder.wait()
    assert (folder / LOCK_NAME).exists()
    with hold_lock(folder, RunDirError):  # not blocked by the file a killed process left
        pass


def test_every_writing_command_refuses_a_held_folder(tmp_path, run):
    spec = Path(shutil.copy(ROOT / "tuning" / f"{IP}.pidlab-robust.toml", tmp_path / "spec.toml"))
    folders = {"exp": tmp_path / "exp", "pipe": tmp_path / "pipe", "new": tmp_path / "new"}
    commands = [
        (run, ["train", IP, "--resume", str(run), "--no-progress"]),
        (folders["new"], ["train", IP, "--coach", "none", "--run-dir", str(folders["new"]), "--no-progress"]),
        (folders["exp"], ["experiment", "--envs", IP, "--conditions", "none", "--seeds", "1", "--out",
                          str(folders["exp"]), "--no-progress"]),
        (folders["pipe"], ["run", IP, "--out", str(folders["pipe"]), "--seeds", "1", "--no-progress"]),
        (spec, ["bounds", str(spec), "--write", "--samples", "5"]),
    ]  # fmt: skip
    for target, args in commands:
        holder = subprocess.Popen(
            [sys.executable, "-c", HOLD, str(target)], stdout=subprocess.PIPE, text=True
        )
        try:
            assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
            before = snapshot(tmp_path)
            code, stderr = cli_in_process(*args)
            lines = stderr.strip().splitlines()
            assert code == 2 and len(lines) == 1, (args, stderr)
            assert lines[0].startswith("pidlab: error: ") and f"(pid {holder.pid})" in lines[0], lines[0]
            assert snapshot(tmp_path) == before, args
        finally:
            holder.kill()
            holder.wait()


def test_two_resumes_of_one_run_one_proceeds(run):
    """A real ``pidlab train --resume`` holds the run; a second one is refused and changes nothing."""
    first = subprocess.Popen(
        [PIDLAB, "train", IP, "--resume", str(run), "--steps", "2000", "--no-progress"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    lock = run / LOCK_NAME
    deadline = time.time() + 120
    while time.time() < deadline and first.poll() is None:
        if lock.exists() and lock.read_text().strip() == str(first.pid):
            break
        time.sleep(0.05)
    assert first.poll() is None, "the first resume ended before the second started"
    code, lines = resume_cli(run, "--steps", "2000")
    assert code == 2 and len(lines) == 1 and f"in use by another pidlab command (pid {first.pid})" in lines[0]
    assert first.wait(timeout=300) == 0, first.stderr.read() if first.stderr else ""
    info = json.loads((run / "run.json").read_text())
    assert len(info["resumes"]) == 1  # the refused command recorded nothing
    summary = json.loads((run / "summary.json").read_text())
    assert summary["completed"] and summary["env_steps"] >= 2000
    assert_logs_consistent(run)
    assert len(read_csv_rows(run / "episodes.csv")) == summary["episodes"]
    assert not lock.exists()


def test_a_killed_resume_does_not_block_the_next(run):
    proc = subprocess.Popen(
        [PIDLAB, "train", IP, "--resume", str(run), "--steps", "100000", "--no-progress"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    deadline = time.time() + 120
    while time.time() < deadline and not (run / LOCK_NAME).exists():
        time.sleep(0.05)
    time.sleep(1.0)
    proc.kill()
    proc.wait()
    assert (run / LOCK_NAME).exists()  # left by the killed process, with its pid
    done = max(state(c)["env_steps"] for c in checkpoint_folders(run))
    code, lines = resume_cli(run, "--steps", str(done + 200))
    assert code == 0, lines
    assert json.loads((run / "summary.json").read_text())["completed"]
    assert_logs_consistent(run)


def _stale_lock(folder: Path) -> tuple[bytes, int]:
    """The lock file a killed command leaves (its pid), dated an hour ago: (its bytes, its mtime)."""
    lock = folder / LOCK_NAME
    lock.write_bytes(b"4194303\n")
    an_hour_ago = time.time_ns() - 3600 * 10**9
    os.utime(lock, ns=(an_hour_ago, an_hour_ago))
    return lock.read_bytes(), lock.stat().st_mtime_ns


def test_a_refusal_puts_back_the_lock_file_a_killed_command_left(tmp_path):
    """A block that ends in an error leaves the lock file as it found it; one that ends well removes it."""
    found = _stale_lock(tmp_path)
    with pytest.raises(RunDirError, match="refused"), hold_lock(tmp_path, RunDirError) as lock:
        assert lock.read_text().strip() == str(os.getpid())  # held: it names this process meanwhile
        raise RunDirError("refused")
    assert (lock.read_bytes(), lock.stat().st_mtime_ns) == found
    with hold_lock(tmp_path, RunDirError):
        pass
    assert not lock.exists()  # a command that ended well removes it, as documented
    with pytest.raises(RunDirError), hold_lock(tmp_path, RunDirError):  # none found: none left
        raise RunDirError("refused")
    assert list(tmp_path.iterdir()) == []


def test_a_refused_resume_changes_nothing_not_even_a_killed_commands_lock_file(run):
    """``--resume`` refused inside the run's lock (--steps below what was done): the lock file stays."""
    (run / "summary.json").unlink()  # as a run that was killed, leaving its lock file
    found = _stale_lock(run)
    before = snapshot(run)
    code, lines = resume_cli(run, "--steps", "300")
    assert code == 2 and len(lines) == 1, lines
    assert "--steps 300: the run has already done" in lines[0], lines
    assert snapshot(run) == before
    assert ((run / LOCK_NAME).read_bytes(), (run / LOCK_NAME).stat().st_mtime_ns) == found


# ---------------------------------------------------------------- the checkpoint fallback


def test_two_checkpoints_are_kept(prepared):
    kept = checkpoint_folders(prepared)
    assert len(kept) == 2 and [p.name for p in (prepared / "checkpoints").iterdir()] != []
    assert {p.name for p in (prepared / "checkpoints").iterdir()} == {p.name for p in kept}
    assert state(kept[0])["env_steps"] < state(kept[1])["env_steps"]


def _garbage(path: Path) -> None:
    path.write_bytes(os.urandom(3000))


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _cut_json(path: Path) -> None:
    path.write_text(path.read_text()[:20])


def _remove(path: Path) -> None:
    path.unlink()


DAMAGES = [
    ("model.zip", _garbage),
    ("model.zip", _truncate),
    ("vecnormalize.npz", _garbage),
    ("vecnormalize.npz", _truncate),
    ("state.json", _cut_json),
    ("model.zip", _remove),
]


@pytest.mark.parametrize(("name", "damage"), DAMAGES, ids=[f"{n}-{d.__name__[1:]}" for n, d in DAMAGES])
def test_a_damaged_latest_checkpoint_falls_back_to_the_previous(run, name, damage):
    previous, latest = checkpoint_folders(run)
    at = state(previous)["env_steps"]
    damage(latest / name)
    (run / "checkpoints" / ".writing").mkdir()  # a checkpoint a kill cut short: ignored, removed
    code, lines = resume_cli(run, "--steps", "800")
    assert code == 0, lines
    warnings = [ln for ln in lines if ln.startswith("pidlab: warning: ")]
    assert len(warnings) == 1 and str(latest / name) in warnings[0], lines
    assert f"resuming from the checkpoint at {at} env steps" in warnings[0]
    entry = json.loads((run / "run.json").read_text())["resumes"][-1]
    assert entry["from_env_steps"] == at
    assert entry["damaged_checkpoints"][0]["env_steps"] == int(latest.name)
    assert name in entry["damaged_checkpoints"][0]["reason"]
    assert not (run / "checkpoints" / ".writing").exists()
    summary = json.loads((run / "summary.json").read_text())
    assert summary["completed"] and summary["env_steps"] >= 800 and summary["resumes"] == 1
    assert_logs_consistent(run)
    assert len(checkpoint_folders(run)) == 2


def test_episodes_cut_before_the_latest_checkpoint_fall_back(run):
    previous, latest = checkpoint_folders(run)
    keep = state(previous)["episodes"] + 1
    assert keep < state(latest)["episodes"]
    lines = (run / "episodes.csv").read_text().splitlines(keepends=True)
    (run / "episodes.csv").write_text("".join(lines[: keep + 1]) + lines[keep + 1][:7])  # cut mid-row
    code, out = resume_cli(run, "--steps", "800")
    assert code == 0, out
    assert len(out) == 1 and "episodes.csv" in out[0] and out[0].startswith("pidlab: warning: ")
    assert_logs_consistent(run)


def _only_one_and_damaged(run: Path) -> None:
    previous, latest = checkpoint_folders(run)
    shutil.rmtree(previous)
    _truncate(latest / "model.zip")


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (lambda run: [_garbage(c / "model.zip") for c in checkpoint_folders(run)], "model.zip: damaged"),
        (lambda run: [_cut_json(c / "state.json") for c in checkpoint_folders(run)], "state.json"),
        (lambda run: _garbage(run / "episodes.csv"), "episodes.csv"),
        (lambda run: (run / "evaluations.csv").write_text("not,a,log\n1,2\n"), "evaluations.csv"),
        (_only_one_and_damaged, "no earlier checkpoint"),
    ],
    ids=["both-models", "both-states", "episodes-garbage", "evaluations-garbage", "only-one-damaged"],
)
def test_no_checkpoint_that_loads_is_one_line_and_changes_nothing(run, damage, message):
    damage(run)
    before = snapshot(run)
    code, lines = resume_cli(run, "--steps", "800")
    assert code == 2 and len(lines) == 1 and lines[0].startswith("pidlab: error: "), lines
    assert "cannot resume" in lines[0] and message in lines[0], lines[0]
    assert snapshot(run) == before


# ---------------------------------------------------------------- damaged run folders


def _recipe_table_removed(run: Path) -> None:
    config = tomllib.loads((run / "config.toml").read_text())
    del config["recipe"]
    (run / "config.toml").write_text(tomli_w.dumps(config))


def _coached_by_garbage(run: Path) -> None:
    text = (run / "config.toml").read_text().replace('name = "none"', 'name = "x"')
    (run / "config.toml").write_text(text)
    _garbage(run / "coach.toml")


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (lambda run: _cut_json(run / "run.json"), "run.json: not a pidlab record"),
        (lambda run: (run / "run.json").write_text('{"command": 5}'), "run.json: not a pidlab record"),
        (_recipe_table_removed, "config.toml: damaged (no [recipe] table"),
        (lambda run: _garbage(run / "config.toml"), "config.toml"),
        (lambda run: _truncate(run / "config.toml"), "config.toml"),
        (_coached_by_garbage, "coach.toml"),
        (lambda run: (run / "coach.toml").write_text("x"), "coach.toml: the run was not coached"),
    ],
    ids=[
        "run-json-cut",
        "run-json-types",
        "config-no-recipe",
        "config-garbage",
        "config-cut",
        "coach-garbage",
        "coach-unexpected",
    ],
)
def test_a_damaged_run_file_is_one_line_naming_it(run, damage, message):
    damage(run)
    before = snapshot(run)
    code, lines = resume_cli(run)
    assert code == 2 and len(lines) == 1 and lines[0].startswith("pidlab: error: "), lines
    assert message in lines[0], lines[0]
    assert snapshot(run) == before


def test_a_damaged_summary_is_written_again(run):
    _garbage(run / "summary.json")
    code, lines = resume_cli(run)
    assert code == 0 and len(lines) == 1 and "summary.json" in lines[0] and "warning" in lines[0], lines
    assert json.loads((run / "summary.json").read_text())["completed"]


def test_a_failed_resume_rewrites_nothing(run):
    """--steps below what was done: refused after every check, before any write."""
    (run / "summary.json").unlink()  # as a run that was killed
    before = snapshot(run)
    code, lines = resume_cli(run, "--steps", "300")
    assert code == 2 and len(lines) == 1 and "--steps 300: the run has already done" in lines[0], lines
    assert snapshot(run) == before


def test_a_damaged_pipeline_stage_file_is_named_before_any_write(tmp_path):
    from pidlab.pipeline import PIPELINE_SCHEMA, _identity, settings_for

    out = tmp_path / "pipe"
    settings = settings_for(IP, seeds=1, steps=1024, roa_samples=40, condition="rescue-terminal")
    write_record(
        out / "pipeline.json", new_record(PIPELINE_SCHEMA, ["pidlab"], identity=_identity(IP, settings))
    )
    (out / "tune.json").write_text('{"cut')
    (out / "tuned.toml").write_text("schema = 1\n")
    before = snapshot(tmp_path)
    code, stderr = cli_in_process("run", IP, "--out", str(out), "--seeds", "1", "--steps", "1024",
                                  "--samples", "40", "--condition", "rescue-terminal", "--no-progress")  # fmt: skip
    lines = stderr.strip().splitlines()
    assert code == 2 and len(lines) == 1, lines
    assert "tune.json" in lines[0] and "redo the tune stage" in lines[0], lines[0]
    assert snapshot(tmp_path) == before


# ---------------------------------------------------------------- a killed sweep


def _descendants(pid: int) -> set[int]:
    """Every process below ``pid`` (from /proc)."""
    parents: dict[int, int] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            text = stat.read_text()
        except OSError:
            continue
        parents[int(stat.parent.name)] = int(text.rsplit(")", 1)[1].split()[1])
    found, todo = set(), [pid]
    while todo:
        p = todo.pop()
        kids = {c for c, pp in parents.items() if pp == p}
        todo += list(kids - found)
        found |= kids
    return found


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_killed_sweep_leaves_no_worker_and_starts_no_run(tmp_path):
    recipe = tiny_recipe(tmp_path, steps=20000, every=500)
    out = tmp_path / "exp"
    cmd = [PIDLAB, "experiment", "--envs", IP, "--conditions", "none,pidlab", "--seeds", "2", "--recipe",
           str(recipe), "--out", str(out), "--workers", "2", "--no-progress"]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    runs = out / "runs" / IP
    deadline = time.time() + 180
    while len(list(runs.glob("*/seed-*/config.toml"))) < 2:  # both workers train a run
        assert proc.poll() is None, proc.stderr.read().decode() if proc.stderr else ""
        assert time.time() < deadline, "the sweep did not start two runs in time"
        time.sleep(0.1)
    children = _descendants(proc.pid)
    started = sorted(str(p.relative_to(runs)) for p in runs.glob("*/seed-*"))
    assert len(children) >= 2 and len(started) == 2
    _sigkill_and_reap(proc, children, poll=0.2)
    assert sorted(str(p.relative_to(runs)) for p in runs.glob("*/seed-*")) == started  # no queued run started



def _sigkill_and_reap(proc: subprocess.Popen, children: list[int], poll: float) -> None:
    """SIGKILL a sweep's main process; its workers must be gone within 15 s."""
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    deadline = time.time() + 15
    while any(_alive(pid) for pid in children) and time.time() < deadline:
        time.sleep(poll)
    assert not [pid for pid in children if _alive(pid)], "processes of the killed sweep are still alive"

ORPHAN_CHILD = """
import os, signal, sys, time
from pidlab.orphans import stop_with_parent
fd = os.open(sys.argv[2], os.O_WRONLY | os.O_APPEND)
signal.signal(signal.SIGTERM, lambda signum, frame: os.write(fd, b"TERM\\n"))  # counts, never dies of it
stop_with_parent(int(sys.argv[1]), lambda: os.kill(os.getpid(), signal.SIGTERM), grace_s=1.0)
print("ready", flush=True)
while True:
    time.sleep(0.01)
"""
THREADED_PARENT = """
import os, subprocess, sys, threading, time
for _ in range(16):  # each thread of the dying parent adopts the child in turn: one death signal each
    threading.Thread(target=time.sleep, args=(600,), daemon=True).start()
child = subprocess.Popen([sys.executable, "-c", sys.argv[1], str(os.getpid()), sys.argv[2]],
                         stdout=subprocess.PIPE, text=True)
child.stdout.readline()
print(child.pid, flush=True)
time.sleep(600)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="prctl(PR_SET_PDEATHSIG) and /proc")
def test_a_parent_death_is_handled_once(tmp_path):
    """A worker whose multi-threaded parent is SIGKILLed is asked to stop once, then exits.

    The kernel sends the death signal whenever the thread that started the worker ends, and again
    each time another thread of the dying parent adopts it; the worker once took the second signal
    as "stop at once" and lost its checkpoint.
    """
    counts = []
    for attempt in range(3):
        log = tmp_path / f"signals-{attempt}.txt"
        log.touch()
        parent = subprocess.Popen([sys.executable, "-c", THREADED_PARENT, ORPHAN_CHILD, str(log)],
                                  stdout=subprocess.PIPE, text=True)  # fmt: skip
        assert parent.stdout is not None
        child = int(parent.stdout.readline())
        parent.kill()
        parent.wait()
        deadline = time.time() + 15
        while _alive(child) and time.time() < deadline:
            time.sleep(0.05)
        assert not _alive(child), "the orphan did not exit within its grace"
        counts.append(log.read_text().count("TERM"))
    assert counts == [1, 1, 1]


def _furthest_episode(run: Path) -> int:
    """The env steps at the end of the run's last logged episode (its complete rows only)."""
    text = (run / "episodes.csv").read_text() if (run / "episodes.csv").exists() else ""
    rows = text.split("\n")[:-1]  # a row still being written has no newline yet
    if len(rows) < 2:
        return 0
    column = rows[0].split(",").index("env_steps_so_far")
    return int(rows[-1].split(",")[column])


SWEEP_WITH_THREADS = """
import sys, threading, time
for _ in range(16):  # a sweep started from a program with threads (a notebook, a Ray driver)
    threading.Thread(target=time.sleep, args=(600,), daemon=True).start()
from pidlab.cli import main
sys.argv = ["pidlab", *sys.argv[1:]]
main()
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_killed_sweep_keeps_every_runs_progress(tmp_path):
    """SIGKILL of a sweep's main process: each worker checkpoints its run where it stopped, then exits.

    Checkpoints are far apart here (every 100,000 env steps, none reached before the kill), so only
    the checkpoint of the stop keeps a run's progress: every run's latest checkpoint is within one
    checkpoint interval of the furthest step it logged, and at or past it (no logged episode lost).
    The sweep's process has more threads than ``pidlab experiment`` alone: the more threads the dying
    process has, the more death signals each worker gets (they had stopped it without a checkpoint).
    """
    every = 100_000
    recipe = tiny_recipe(tmp_path, steps=4 * every, every=every)
    out = tmp_path / "exp"
    cmd = [sys.executable, "-c", SWEEP_WITH_THREADS, "experiment", "--envs", IP, "--conditions", "none",
           "--seeds", "3", "--recipe", str(recipe), "--out", str(out), "--workers", "3", "--no-progress"]  # fmt: skip
    with open(tmp_path / "stderr.txt", "w") as err:
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err, start_new_session=True)
    runs = [out / "runs" / IP / "none" / f"seed-{s}" for s in (0, 1, 2)]
    deadline = time.time() + 120
    while min(_furthest_episode(r) for r in runs) < 500:  # both runs under way
        assert proc.poll() is None, (tmp_path / "stderr.txt").read_text()
        assert time.time() < deadline, "the sweep did not get both runs under way in time"
        time.sleep(0.1)
    children = _descendants(proc.pid)
    _sigkill_and_reap(proc, children, poll=0.1)
    for run in runs:
        furthest = _furthest_episode(run)
        kept = checkpoint_folders(run)
        assert kept, f"{run.name}: no checkpoint; {furthest} env steps lost"
        latest = state(kept[-1])["env_steps"]
        assert furthest <= latest <= furthest + every, (run.name, furthest, latest)
    assert "Traceback" not in (tmp_path / "stderr.txt").read_text()


def test_a_damaged_finished_run_is_one_line_in_the_report(tmp_path):
    """experiment --report-only over a run whose summary or logs were damaged: an ExperimentError naming it."""
    from pidlab.errors import ExperimentError
    from pidlab.experiment.analysis import load_run
    from pidlab.experiment.metrics import Rule

    rule = Rule(800.0, 5, 20, 5000, 10)
    run = tmp_path / "seed-0"
    run.mkdir()
    summary = {"env_steps": 10, "agent_steps": 10, "coach_steps": 0, "completed": True}
    (run / "summary.json").write_text(json.dumps(summary))
    (run / "episodes.csv").write_text("episode,agent_return\n0,not-a-number\n")
    with pytest.raises(ExperimentError, match="seed-0: the finished run's logs are damaged"):
        load_run(run, "InvertedPendulum-v5", "none", 0, rule)
    (run / "episodes.csv").unlink()  # a log file gone
    with pytest.raises(ExperimentError, match="seed-0: the finished run's logs are damaged"):
        load_run(run, "InvertedPendulum-v5", "none", 0, rule)
    (run / "summary.json").write_text(json.dumps({**summary, "policy_updates": -3}))  # a count that cannot be
    (run / "episodes.csv").write_text("episode,env_steps_so_far,agent_return,total_return,coach_steps\n")
    (run / "evaluations.csv").write_text("env_steps_so_far,agent_steps_so_far,mean_return,mean_length,returns\n")
    with pytest.raises(ExperimentError, match="policy_updates = -3"):
        load_run(run, "InvertedPendulum-v5", "none", 0, rule)
    (run / "summary.json").write_text(json.dumps(summary))
    with pytest.raises(ExperimentError, match="no evaluation of the finished run"):
        load_run(run, "InvertedPendulum-v5", "none", 0, rule)
    header = "env_steps_so_far,agent_steps_so_far,mean_return,mean_length,returns\n"
    (run / "evaluations.csv").write_text(header + "10,10,5.0,5.0,5.0\n")
    (run / "summary.json").write_text(json.dumps({**summary, "episodes": 3, "evaluations": 1}))
    with pytest.raises(ExperimentError, match="episodes.csv holds 0 of the 3 episodes summary.json records"):
        load_run(run, "InvertedPendulum-v5", "none", 0, rule)  # a log cut short: numbers would be wrong
    (run / "summary.json").write_text(json.dumps({**summary, "episodes": 0, "evaluations": 2}))
    with pytest.raises(ExperimentError, match="evaluations.csv holds 1 of the 2 evaluations summary.json records"):
        load_run(run, "InvertedPendulum-v5", "none", 0, rule)
    (run / "summary.json").write_text(json.dumps({**summary, "completed": False}))  # stopped early: not counted
    assert not load_run(run, "InvertedPendulum-v5", "none", 0, rule).completed
    (run / "summary.json").write_text('{"env_steps": 1')
    with pytest.raises(ExperimentError, match="summary.json: the run summary is damaged"):
        load_run(run, "InvertedPendulum-v5", "none", 0, rule)
