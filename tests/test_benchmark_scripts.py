"""The benchmark scripts' command lines: bad input is one line and exit code 2 (benchmarks/bench_cli.py).

The argument types are checked against hand-picked values; every script is run with an unknown flag
and the scripts whose input pidlab itself checks with a value it refuses, in this process (runpy), so
that no case pays for a fresh interpreter.
"""

from __future__ import annotations

import argparse
import ast
import runpy
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"
sys.path.insert(0, str(BENCH))

import bench_cli  # noqa: E402

SCRIPTS = sorted(
    p for p in BENCH.glob("*.py") if p.name != "bench_cli.py" and '__name__ == "__main__"' in p.read_text()
)
PARSERS = [p for p in SCRIPTS if "Parser(" in p.read_text()]


def _run(script: Path, args: list[str], monkeypatch, capsys) -> tuple[int, list[str]]:
    """Run a script as ``python script args``; its exit code and its stderr's lines."""
    import signal

    monkeypatch.setattr(sys, "argv", [str(script), *args])
    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        with pytest.raises(SystemExit) as stop:
            runpy.run_path(str(script), run_name="__main__")
    finally:  # a script ignores both once it has ended, as the process it is would exit then
        assert all(signal.getsignal(sig) == signal.SIG_IGN for sig in handlers)
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
    return stop.value.code, capsys.readouterr().err.strip().splitlines()


@pytest.mark.parametrize(("text", "value"), [("1", 1), ("20000", 20000), ("+3", 3)])
def test_count_accepts_whole_numbers_from_one(text, value):
    assert bench_cli.count(text) == value


@pytest.mark.parametrize("text", ["0", "-3", "2.5", "x", "", "nan"])
def test_count_refuses_the_rest(text):
    with pytest.raises(argparse.ArgumentTypeError, match="whole number >= 1"):
        bench_cli.count(text)


def test_counts_reads_a_comma_list_and_refuses_a_bad_item():
    assert bench_cli.counts("1,2") == [1, 2]
    assert bench_cli.counts(" 4 ") == [4]
    with pytest.raises(argparse.ArgumentTypeError, match="'0'"):
        bench_cli.counts("1,0")


@pytest.mark.parametrize("text", ["0", "-1", "inf", "nan", "x"])
def test_positive_refuses_zero_negatives_and_non_finite(text):
    with pytest.raises(argparse.ArgumentTypeError, match="finite number > 0"):
        bench_cli.positive(text)


def test_seconds_takes_zero_but_not_negatives():
    assert bench_cli.positive("0.5") == 0.5
    assert bench_cli.seconds("0") == 0.0
    for text in ("-0.1", "inf", "nan", "soon"):
        with pytest.raises(argparse.ArgumentTypeError, match="seconds >= 0"):
            bench_cli.seconds(text)


def test_names_keeps_the_list_as_text_and_refuses_unknown_or_repeated_names():
    parse = bench_cli.names(("IP", "Hopper"))
    assert parse("IP, Hopper") == "IP,Hopper"
    with pytest.raises(argparse.ArgumentTypeError, match="'Walker'"):
        parse("IP,Walker")
    with pytest.raises(argparse.ArgumentTypeError, match="twice"):
        parse("IP,IP")


def test_every_script_ends_through_bench_cli_run():
    """A script whose ``__main__`` block bypasses :func:`bench_cli.run` would print tracebacks for bad input."""
    for script in SCRIPTS:
        tree = ast.parse(script.read_text())
        block = next(n for n in tree.body if isinstance(n, ast.If) and "__main__" in ast.unparse(n.test))
        calls = {ast.unparse(c.func) for c in ast.walk(block) if isinstance(c, ast.Call)}
        assert calls & {"run", "run_script"}, f"{script.name}: its __main__ block does not call bench_cli.run"


@pytest.mark.parametrize("script", PARSERS, ids=lambda p: p.name)
def test_an_unknown_flag_is_one_line_and_exit_2(script, monkeypatch, capsys):
    code, err = _run(script, ["--no-such-flag"], monkeypatch, capsys)
    assert code == 2
    assert len(err) == 1, err  # a script with a required argument names that first
    assert err[0].startswith(f"{script.name}: error: ")
    assert err[0].endswith(f"(see {script.name} --help)")
    assert "unrecognized arguments: --no-such-flag" in err[0] or "arguments are required" in err[0]


@pytest.mark.parametrize(
    ("name", "args", "says"),
    [
        ("coach_scores.py", ["--episodes", "-3"], "argument --episodes: '-3': expected a whole number >= 1"),
        ("coverage_table.py", ["--envs", "Foo-v5"], "argument --envs: 'Foo-v5': expected names among"),
        ("shield_floor.py", ["--episodes", "0"], "argument --episodes: '0': expected a whole number >= 1"),
        ("beyond_the_coach.py", ["x.toml", "--states", "0"], "argument --states: '0': expected a whole number >= 1"),
        (
            "beyond_the_coach.py",
            [str(BENCH.parent / "tuning" / "Hopper-v5.pidlab-room.toml")],
            "the spec's coach has no certified core (an ellipsoid) to rescue into",
        ),
        ("region_speed.py", ["--workers", "1,x"], "argument --workers: 'x': expected a whole number >= 1"),
        (
            "tuner_load.py",
            ["--settle", "-1"],
            "argument --settle: '-1': expected a finite number of seconds >= 0",
        ),
        (
            "one_step_room.py",
            ["InvertedPendulum-v5", "x.toml", "--policy-std", "0"],
            "expected a finite number > 0",
        ),
        # checked by pidlab itself, the error raised inside main()
        (
            "rescue_settle.py",
            ["Hopper-v5", "/nonexistent/coach.toml"],
            "cannot read coach spec '/nonexistent/coach.toml'",
        ),
        ("coaching_throughput.py", ["--envs", "Nope-v5"], "cannot read recipe"),
        ("model_trigger_latency.py", ["--pieces", "64,0"], "argument --pieces: '0': expected a whole number >= 1"),
        ("recompute.py", ["/nonexistent"], "/nonexistent: cannot be read"),
        ("repeat_runs.py", ["/nonexistent", "/nonexistent", "X-v0", "c"], "no such run folder"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(name, args, says, monkeypatch, capsys):
    code, err = _run(BENCH / name, args, monkeypatch, capsys)
    assert code == 2
    assert len(err) == 1 and says in err[0], err
    assert "Traceback" not in err[0]


def test_a_child_process_error_is_said_once(tmp_path):
    """sac_throughput.py measures in child processes: the child's one line becomes the script's."""
    done = subprocess.run(
        [
            sys.executable,
            str(BENCH / "sac_throughput.py"),
            "--envs",
            "Nope-v5",
            "--repeats",
            "1",
            "--steps",
            "10",
            "--out",
            str(tmp_path / "page.md"),
        ],
        capture_output=True,
        text=True,
        check=False,
        timeout=300,
    )
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [
        f"sac_throughput.py: error: cannot read recipe '{ROOT / 'coach' / 'Nope-v5.toml'}': No such file or directory"
    ]
    assert not (tmp_path / "page.md").exists()


def test_run_accounts_by_hand(tmp_path):
    """benchmarks/run_accounts.py on two hand-written runs: the sums and ranges a reading cites."""
    import json

    import run_accounts

    head = "episode,env_steps_so_far,agent_steps_so_far,agent_steps,coach_steps,interventions,agent_return,"
    head += "total_return,terminated,env_index,env_end,fell,runs,longest_run\n"
    # seed-0: a fall with no takeover, a fall after one, a takeover without a fall
    first = ["0,10,10,10,0,0,10,10,1,0,1,1,1,10", "1,40,20,10,20,1,10,30,1,0,1,1,1,10"]
    first.append("2,60,30,10,10,1,10,20,1,0,0,0,1,10")
    runs = {
        "seed-0": (first, 3, 60, 30, 5, 0, 12, 7.5),
        "seed-1": (["0,20,20,20,0,0,20,20,1,0,1,1,1,20"], 1, 20, 0, 0, 4, 3, 2.5),
    }
    for seed, (rows, falls, env, coach, vetoes, picked, updates, wall) in runs.items():
        d = tmp_path / "runs" / "X-v0" / "c" / seed
        d.mkdir(parents=True)
        (d / "episodes.csv").write_text(head + "\n".join(rows) + "\n")
        (d / "config.toml").write_text('[recipe.coaching]\nview = "terminal"\n')
        (d / "summary.json").write_text(json.dumps({
            "completed": True, "falls": falls, "env_steps": env, "coach_steps": coach, "value_vetoes": vetoes,
            "proposals_taken": picked, "policy_updates": updates, "wall_s_total": wall,
        }))  # fmt: skip
    (tmp_path / "runs" / "X-v0" / "c" / "seed-2").mkdir()  # unfinished: no summary.json, left out
    stopped = tmp_path / "runs" / "X-v0" / "c" / "seed-3"  # stopped by a signal: completed false, left out
    stopped.mkdir()
    (stopped / "summary.json").write_text(json.dumps({"completed": False, "falls": 99}))
    got = run_accounts.folder_accounts(tmp_path)
    assert list(got) == [("X-v0", "c")]
    a, b = got[("X-v0", "c")]
    assert a == run_accounts.RunAccounts(3, 1, 60, 30, 5, 0, 12, 7.5)
    assert b == run_accounts.RunAccounts(1, 0, 20, 0, 0, 4, 3, 2.5)
    row = run_accounts.table(got)[2]
    assert (
        row
        == "| X-v0 | c | 2 | 1 to 3 | 0 to 1 | 0.0 % to 50.0 % | 0 to 5 | 0 to 4 | 0.15 to 0.20 | 2 to 8 |"
    )


def test_repeat_runs_by_hand(tmp_path):
    """benchmarks/repeat_runs.py: the first differing evaluation, the resumes and SHAs, finished seeds only."""
    import json

    import repeat_runs

    head = "env_steps_so_far,mean_return\n"
    runs = {  # (experiment, seed): evaluation rows, resumes, sha, completed
        ("short", 0): (["0,1.0", "10,2.0"], [], "a" * 40, True),
        ("long", 0): (["0,1.0", "10,2.0", "20,3.0"], [], "b" * 40, True),
        ("short", 1): (["0,1.0", "10,2.5"], [{"from_env_steps": 7}], "a" * 40, True),
        ("long", 1): (["0,1.0", "10,2.0", "20,3.0"], [], "b" * 40, True),
        ("short", 2): (["0,1.0"], [], "a" * 40, False),  # stopped: left out
        ("long", 2): (["0,1.0"], [], "b" * 40, True),
    }
    for (where, seed), (rows, resumes, sha, completed) in runs.items():
        d = tmp_path / where / "runs" / "X-v0" / "c" / f"seed-{seed}"
        d.mkdir(parents=True)
        (d / "evaluations.csv").write_text(head + "\n".join(rows) + "\n")
        (d / "run.json").write_text(json.dumps({"git": {"sha": sha}, "resumes": resumes}))
        (d / "summary.json").write_text(json.dumps({"completed": completed}))
    short, long = (tmp_path / w / "runs" / "X-v0" / "c" for w in ("short", "long"))
    assert repeat_runs._seeds(short) == {0, 1}
    assert repeat_runs.compare(short, long, 0) == repeat_runs.Repeat(0, 2, None, ((), ()), ("a" * 12, "b" * 12))
    one = repeat_runs.compare(short, long, 1)
    assert one.first_difference == 10 and one.resumes == ((7,), ())
    rows = repeat_runs.table([repeat_runs.compare(short, long, s) for s in (0, 1)]).splitlines()
    assert rows[2] == f"| 0 | 2 | none: identical | - / - | {'a' * 12} / {'b' * 12} |"
    assert rows[3] == f"| 1 | 2 | 10 | 7 / - | {'a' * 12} / {'b' * 12} |"
    # damaged files are named in one line, not a traceback
    from pidlab.errors import ExperimentError

    (long / "seed-0" / "evaluations.csv").write_text(head + "x,2.0\n")
    with pytest.raises(ExperimentError, match="row 1 does not start with an env step"):
        repeat_runs.compare(short, long, 0)
    (short / "seed-1" / "run.json").write_text(json.dumps({"git": {}, "resumes": [{}]}))
    with pytest.raises(ExperimentError, match="a resume without its env step"):
        repeat_runs.compare(short, long, 1)
    (short / "seed-0" / "summary.json").write_text('{"completed": tr')
    with pytest.raises(ExperimentError, match="run summary is damaged"):
        repeat_runs._seeds(short)
