"""``pidlab run``: the whole pipeline, end to end with a tiny budget, resumed, and refused."""

from __future__ import annotations

import json
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pidlab.controller.spec import load_spec
from pidlab.pipeline import RESCUE_JOURNAL
from pidlab.region.journal import CHUNK
from pidlab.rl.recipe import RecipeError, load_pipeline_settings, parse_pipeline
from pidlab.rl.rundir import spec_digest
from tests.helpers import cli_in_process

ROOT = Path(__file__).resolve().parents[1]
TINY = ["--seeds", "1", "--steps", "1024", "--samples", "40", "--episodes", "1", "--workers", "2",
        "--condition", "rescue-terminal"]  # fmt: skip
"""A tiny pipeline, shielding without a warm start (the recipe's warm start needs 2,500 env steps)."""


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "pidlab", "run", *args], capture_output=True, text=True, timeout=600
    )


def _without_timings(report: str) -> list[str]:
    """The report but its command line (it counts resumes) and its stage-time rows."""
    stage_row = re.compile(r"^\| (linearize|tune|analyze|bounds|train|report) \|")
    return [ln for ln in report.splitlines() if not ln.startswith("Command:") and not stage_row.match(ln)]


def _interrupted_in_training(out: Path) -> subprocess.CompletedProcess[str]:
    """Start the pipeline, SIGTERM it once it trains (workers starting or running)."""
    argv = [
        sys.executable,
        "-m",
        "pidlab",
        "run",
        "InvertedPendulum-v5",
        "--out",
        str(out),
        *TINY,
        "--no-progress",
    ]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    seen = []
    for line in proc.stdout:
        seen.append(line)
        if line.startswith("[5/6] train ..."):
            time.sleep(3.0)
            proc.send_signal(signal.SIGTERM)
            break
    out_text, err = proc.communicate(timeout=300)
    return subprocess.CompletedProcess(argv, proc.returncode, "".join(seen) + out_text, err)


def _interrupted_in_the_rescue_region(out: Path) -> subprocess.CompletedProcess[str]:
    """Start the pipeline, SIGTERM it once its bounds stage has journaled rescue simulations."""
    argv = [sys.executable, "-m", "pidlab", "run", "InvertedPendulum-v5", "--out", str(out), *TINY, "--no-progress"]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 300
    while not any((out / RESCUE_JOURNAL).glob("*/chunk-*.npz")):
        assert proc.poll() is None and time.monotonic() < deadline, "the bounds stage kept no journal"
        time.sleep(0.1)
    proc.send_signal(signal.SIGTERM)
    out_text, err = proc.communicate(timeout=300)
    return subprocess.CompletedProcess(argv, proc.returncode, out_text, err)


def test_pipeline_end_to_end_interrupted_resumed(tmp_path):
    out = tmp_path / "ip"
    # killed in its rescue region: the simulations done are kept and read back on resuming
    stopped = _interrupted_in_the_rescue_region(out)
    assert stopped.returncode == 130, stopped.stderr[-2000:]
    assert "run the same command to resume" in stopped.stderr and "Traceback" not in stopped.stderr
    assert not (out / "coach.toml").exists() and (out / RESCUE_JOURNAL).is_dir()
    # killed while it trains: exit 130, one line saying how to resume, no traceback (not even a worker's)
    stopped = _interrupted_in_training(out)
    assert stopped.returncode == 130, stopped.stderr[-2000:]
    assert "run the same command to resume" in stopped.stderr and "Traceback" not in stopped.stderr
    assert (out / "coach.toml").is_file() and not (out / "report.md").exists()
    assert "train" not in json.loads((out / "pipeline.json").read_text()).get("stages", {})

    done = _run("InvertedPendulum-v5", "--out", str(out), *TINY, "--no-progress")
    assert done.returncode == 0, done.stderr[-2000:]
    assert "tune: done before, skipped" in done.stdout and "bounds: done before, skipped" in done.stdout
    assert f"report: {out / 'report.html'}" in done.stdout
    for name in ("pipeline.json", "linearization.json", "tuned.toml", "tune.json", "coach.toml", "roa.json",
                 "conditions.toml", "report.md", "report.html", "experiment/report.md",
                 "figures/roa.png", "figures/rescue.png", "figures/learning-curves.png",
                 "figures/bode_slide.png", "figures/responses.png"):  # fmt: skip
        assert (out / name).is_file(), name

    # the coach that trained is the tuned one plus the derived bounds, and they are the report's
    tuned, coached = load_spec(out / "tuned.toml"), load_spec(out / "coach.toml")
    assert [lp.kp for lp in tuned.loops] == [lp.kp for lp in coached.loops]
    assert tuned.bounds is None and coached.bounds is not None
    roa = json.loads((out / "roa.json").read_text())
    assert roa["check"]["samples"] == 40
    assert {k: list(v) for k, v in coached.bounds["box"].items()} == roa["bounds"]["box"]
    # the recipe's condition (rescue-terminal) takes over outside the coach's validated rescue region
    assert coached.bounds["takeover"] == "rescue" and roa["rescue"]["validation"]["failures"] == 0
    assert roa["rescue"]["reused"] >= CHUNK and not (out / RESCUE_JOURNAL).exists()  # read back, then removed
    assert list(coached.bounds["rescue"]["variables"]) == roa["rescue"]["variables"]
    assert json.loads((out / "tune.json").read_text())["preset"] == "room"
    runs = out / "experiment" / "runs" / "InvertedPendulum-v5"
    cfg = (runs / "coached" / "seed-0" / "config.toml").read_text()
    assert spec_digest(coached) in cfg
    assert 'view = "terminal"' in cfg and 'trigger = "predictive"' in cfg
    assert 'name = "none"' in (runs / "none" / "seed-0" / "config.toml").read_text()
    for cond in ("none", "coached"):
        summary = json.loads((runs / cond / "seed-0" / "summary.json").read_text())
        assert summary["env_steps"] >= 1024

    report = (out / "report.md").read_text()
    for needle in ("## 1. The linear model", "| loop broken at | gain margin (dB) |", "phase margin (deg)", "rad/s",
                   "## 3. Region of attraction", "40 sampled initial states", "figures/roa.png",
                   "figures/learning-curves.png", "| none |", "| coached |", "final agent-alone score",
                   "### Rescue region: the takeover region", "figures/rescue.png", "falls during training",
                   "condition `rescue-terminal`", "## 5. Why this coaching"):  # fmt: skip
        assert needle in report, needle
    # the numbers are the analysis' own: the margins row of the coach, the one-step fraction
    from pidlab.controller.analysis import analyze_coach, margin_table
    from pidlab.controller.pid import Coach
    from pidlab.plant.model import load_model

    loaded = load_model("InvertedPendulum-v5")
    row = margin_table(analyze_coach(Coach(tuned, loaded), loaded).discrete.margins)[0]
    line = next(ln for ln in report.splitlines() if ln.startswith(f"| {row['actuator']} |"))
    cells = [c.strip() for c in line.strip("|").split("|")]
    assert cells[3] == f"{row['pm_deg']:.1f}" and cells[4] == f"{row['delay_ms']:.1f}"
    assert cells[8] == f"{row['ms_db']:.2f}"
    fraction = roa["bounds"]["one_step_action_fraction"]
    assert ("for agent actions up to" in report) == (fraction < 1.0)
    record = json.loads((out / "pipeline.json").read_text())
    assert record["identity"]["settings"]["steps"] == 1024 and len(record["resumes"]) == 2  # stopped twice
    assert record["git"]["sha"] and record["versions"]["mujoco"]
    assert record["schema"] == "pidlab.pipeline/1" and record["created"]
    assert record["command"][:2] == ["pidlab", "run"]
    assert record["resumes"][0]["at"] and record["resumes"][0]["versions"] and record["resumes"][0]["git"]
    assert set(record["stages"]) == {"linearize", "tune", "analyze", "bounds", "train", "report"}

    # the same command again: tune and bounds are not redone, no run is retrained, same report
    before = {p: (out / p).read_bytes() for p in ("tuned.toml", "coach.toml", "roa.json")}
    model = runs / "coached" / "seed-0" / "final_model.zip"
    mtime = model.stat().st_mtime_ns
    again = _run("InvertedPendulum-v5", "--out", str(out), *TINY, "--no-progress")
    assert again.returncode == 0, again.stderr[-2000:]
    assert "tune: done before, skipped" in again.stdout and "bounds: done before, skipped" in again.stdout
    assert {p: (out / p).read_bytes() for p in before} == before
    assert model.stat().st_mtime_ns == mtime
    assert _without_timings(report) == _without_timings((out / "report.md").read_text())
    assert len(json.loads((out / "pipeline.json").read_text())["resumes"]) == 3

    # other settings in the same folder: refused, one line, nothing touched
    code, err = cli_in_process("run", "InvertedPendulum-v5", "--out", str(out), *TINY[:2], "--steps", "2048",
                               *TINY[-2:])  # fmt: skip
    assert code == 2
    assert "other settings" in err and "steps 1024 (now 2048)" in err and len(err.strip().splitlines()) == 1
    assert {p: (out / p).read_bytes() for p in before} == before


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["NoSuchEnv-v0"], "no recipe"),
        (["InvertedPendulum-v5", "--seeds", "0"], "--seeds 0: expected an integer in [1, 10000]"),
        (["InvertedPendulum-v5", "--steps", "-5"], "--steps -5"),
        (
            ["InvertedPendulum-v5", "--preset", "strong"],
            "--preset 'strong': expected one of robust, weak, room, balance",
        ),
        (["InvertedPendulum-v5", "--condition", "nope"], "--condition 'nope': not a condition of"),
        (["InvertedPendulum-v5", "--condition", "none"], "--condition 'none': trains no coach"),
        (
            ["InvertedPendulum-v5", "--condition", "rescue-replay"],
            "--condition 'rescue-replay': names its own algorithm (sac)",
        ),
        (["InvertedPendulum-v5", "--workers", "0"], "--workers 0"),
        # the recipe's condition demonstrates for 2,500 env steps: refused before any stage runs
        (
            ["InvertedPendulum-v5", "--steps", "2000"],
            "--steps 2000: the condition 'warm-start-keep-shield-short'",
        ),
        (["InvertedPendulum-v5", "--samples", "0"], "--samples 0"),
        # checked before anything is written (it had written linearization.json and pipeline.json first)
        (
            ["Hopper-v5", "--preset", "room"],
            "--preset 'room': on Hopper-v5 the room preset searches the gains on the env; run it alone with "
            "`pidlab tune Hopper-v5 --auto --preset room` (the pipeline uses it on the pendulums only); "
            "expected one of robust, weak, balance",
        ),
        (
            ["InvertedPendulum-v5", "--preset", "balance"],
            "--preset 'balance': InvertedPendulum-v5's model card has no [balance] table (the balance preset "
            "poses a robot on its feet); expected one of robust, weak, room",
        ),
    ],
)
def test_bad_input_is_one_line_and_exit_2(tmp_path, args, message):
    code, err = cli_in_process("run", *args, "--out", str(tmp_path / "x"))
    assert code == 2
    assert message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x").exists()


def test_an_out_that_is_a_file_is_refused(tmp_path):
    (tmp_path / "f").write_text("mine")
    code, err = cli_in_process("run", "InvertedPendulum-v5", "--out", str(tmp_path / "f"))
    assert code == 2 and "exists and is not a folder" in err
    code, err = cli_in_process("run", "InvertedPendulum-v5", "--out", str(tmp_path / "f" / "sub"))
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert (tmp_path / "f").read_text() == "mine"


def test_a_folder_that_is_not_a_pipeline_is_refused(tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    code, err = cli_in_process("run", "InvertedPendulum-v5", "--out", str(tmp_path))
    assert code == 2 and "holds no pipeline.json" in err
    assert [p.name for p in tmp_path.iterdir()] == ["notes.txt"]


def test_a_folder_of_other_settings_is_refused_with_commands_that_work(tmp_path):
    """The refusal names another --out and the folder removed; the folder's own command only when it runs.

    A folder left by a refusal (``--preset room`` on Hopper-v5, before that was checked first) had
    been advised "run with the same settings to resume": the command that refuses.
    """
    from dataclasses import replace

    from pidlab.pipeline import PIPELINE_SCHEMA, _identity, check_out_folder, settings_for
    from pidlab.provenance import new_record, write_record

    def folder(name: str, env: str, settings: object, command: list[str]) -> Path:
        out = tmp_path / name
        write_record(
            out / "pipeline.json", new_record(PIPELINE_SCHEMA, command, identity=_identity(env, settings))
        )
        (out / "linearization.json").write_text("{}")
        return out

    room = replace(settings_for("Hopper-v5"), preset="room")  # what the refusal left behind
    stuck = folder("stuck", "Hopper-v5", room, ["pidlab", "run", "Hopper-v5", "--preset", "room"])
    code, err = cli_in_process("run", "Hopper-v5", "--out", str(stuck), "--no-progress")
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1, err
    assert "other settings (preset room (now robust))" in lines[0] and "nothing was changed" in lines[0]
    assert (
        f"Choose another folder (--out), or remove this one (rm -r {stuck}) and run this command again"
        in lines[0]
    )
    assert "--preset room" not in lines[0]  # its own command is refused: not advised
    shutil.rmtree(stuck)  # what the line says; the command's checks then pass
    assert check_out_folder(stuck, _identity("Hopper-v5", settings_for("Hopper-v5"))) is None

    shield = ["--condition", "rescue-terminal"]  # budgets below the recipe's 2,500 demonstration steps
    own = ["pidlab", "run", "InvertedPendulum-v5", "--steps", "1024", *shield]
    settings = settings_for("InvertedPendulum-v5", steps=1024, condition="rescue-terminal")
    other = folder("other", "InvertedPendulum-v5", settings, own)
    before = {p.name: p.read_bytes() for p in other.iterdir()}
    code, err = cli_in_process("run", "InvertedPendulum-v5", "--out", str(other), "--steps", "2048", *shield)
    assert code == 2 and "steps 1024 (now 2048)" in err, err
    assert (
        "Resume it with its own command (pidlab run InvertedPendulum-v5 --steps 1024 --condition "
        "rescue-terminal), choose another" in err
    )
    assert {p.name: p.read_bytes() for p in other.iterdir()} == before


def test_recipe_pipeline_table_defaults_and_errors(tmp_path, monkeypatch):
    base = {"schema": "pidlab.recipe/1", "env_id": "X-v0", "steps": 5000, "ppo": {}}
    s = parse_pipeline(base)
    assert (s.seeds, s.steps, s.preset, s.roa_samples, s.episodes) == (3, 5000, "robust", 1000, 10)
    assert s.condition == "pidlab"
    with pytest.raises(RecipeError, match=r"recipe\.pipeline\.condition"):
        parse_pipeline({**base, "pipeline": {"condition": "../x"}})
    with pytest.raises(
        RecipeError, match=r"recipe\.pipeline\.seeds = 0: expected an integer in \[1, 10000\]"
    ):
        parse_pipeline({**base, "pipeline": {"seeds": 0}})
    with pytest.raises(RecipeError, match="unknown field"):
        parse_pipeline({**base, "pipeline": {"budget": 3}})
    for env in ("InvertedPendulum-v5", "InvertedDoublePendulum-v5", "Hopper-v5", "Walker2d-v5"):
        assert load_pipeline_settings(ROOT / "coach" / f"{env}.toml").seeds >= 1
    # a bad [pipeline] in the recipe of the env asked for: one line, exit 2
    text = (
        (ROOT / "coach" / "InvertedPendulum-v5.toml").read_text().replace('preset = "room"', 'preset = "x"')
    )
    (tmp_path / "InvertedPendulum-v5.toml").write_text(text)
    monkeypatch.setenv("PIDLAB_COACH", str(tmp_path))
    code, err = cli_in_process("run", "InvertedPendulum-v5", "--out", str(tmp_path / "o"))
    assert code == 2 and "pipeline.preset = 'x'" in err


def test_the_report_says_why_with_the_published_numbers():
    import csv
    from types import SimpleNamespace

    from pidlab.pipeline import published_evidence
    from pidlab.report.pipeline import evidence_section

    ev = published_evidence("InvertedPendulum-v5", "rescue-terminal")
    # the confirmation (the analysis plan's fresh seeds) is preferred to the pilot sweeps
    assert ev is not None and ev.folder == "docs/results/InvertedPendulum-v5-confirm"
    with open(ROOT / ev.folder / "summary.csv", newline="") as f:
        falls = next(
            r for r in csv.DictReader(f) if r["condition"] == "rescue-terminal" and r["metric"] == "falls"
        )
    assert ev.rows[("rescue-terminal", "falls")] == falls
    from dataclasses import replace

    settings = replace(
        load_pipeline_settings(ROOT / "coach" / "InvertedPendulum-v5.toml"), condition="rescue-terminal"
    )
    facts = SimpleNamespace(env_id="InvertedPendulum-v5", evidence=ev, settings=settings)  # what it reads
    text = "\n".join(evidence_section(facts))
    assert f"`{ev.folder}`" in text and "| rescue-terminal |" in text and "| none |" in text
    iqm = float(falls["iqm"])
    assert f"| rescue-terminal | {iqm:,.1f} [" in text
    # an exploratory sweep on the same seeds (a condition the plan does not govern) is not preferred
    # for the plan's conditions, and is the evidence for its own
    model = published_evidence("InvertedPendulum-v5", "rescue-terminal-model")
    assert model is not None and model.folder == "docs/results/InvertedPendulum-v5-model"
    # a condition no published experiment compares with none: said plainly
    assert published_evidence("InvertedPendulum-v5", "no-such-condition") is None
    facts.evidence = None
    assert "No published experiment" in "\n".join(evidence_section(facts))


@pytest.mark.parametrize(
    ("env_id", "folder"),
    [
        ("InvertedPendulum-v5", "docs/results/InvertedPendulum-v5-teach4"),
        ("InvertedDoublePendulum-v5", "docs/results/InvertedDoublePendulum-v5-teach7"),
        ("Hopper-v5", "docs/results/Hopper-v5-teach6"),
    ],
)
def test_the_main_job_uses_the_coupling_its_confirmation_supports(env_id, folder):
    """The recipe names a condition its fresh-seed sweep found safer and on no primary measure worse.

    Walker2d keeps the default: each coupling measured there is worse on an agent-alone measure.
    """
    import csv

    from pidlab.pipeline import published_evidence, settings_for

    condition = settings_for(env_id).condition
    ev = published_evidence(env_id, condition)
    assert ev is not None and ev.folder == folder
    primary = ("falls", "env_steps_to_alone_target", "final_score")
    with open(ROOT / folder / "summary.csv", newline="") as f:
        verdicts = {
            r["metric"]: r["verdict"]
            for r in csv.DictReader(f)
            if r["condition"] == condition and r["env"] == env_id and r["metric"] in primary
        }
    assert set(verdicts) == set(primary)
    assert verdicts["falls"] == "better" and "worse" not in verdicts.values()


@pytest.mark.parametrize(
    ("keep", "says"),
    [
        ({"shape": "constant", "start": 1.0, "end": 1.0}, "at a weight held at 1 for the whole budget"),
        ({"shape": "linear", "start": 1.0, "end": 0.0, "begin": 0.0, "finish": 1.0}, "fades from 1 to 0"),
        ({"shape": "linear", "start": 1.0, "end": 0.5, "begin": 0.0, "finish": 1.0}, "goes from 1 to 0.5"),
    ],
)
def test_the_report_says_how_the_demonstrations_weigh_in_the_updates(keep, says):
    from pidlab.report.pipeline import _teaching_text

    text = _teaching_text({"demonstrations": {"steps": 20000, "noise": 0.1}, "warm_start": {"keep": keep}})
    assert "demonstrates for 20,000 env steps" in text and says in text
    assert ("fades" in text) is (keep["end"] == 0.0 and keep["start"] != 0.0)


def test_no_coupling_measured_on_walker2d_passes_the_main_jobs_rule():
    """Walker2d's recipe keeps the default coaching because every measured coupling costs the agent."""
    import csv

    from pidlab.pipeline import settings_for

    assert settings_for("Walker2d-v5").condition == "pidlab"
    primary = ("falls", "env_steps_to_alone_target", "final_score")
    seen = set()
    for folder in ("Walker2d-v5-confirm", "Walker2d-v5-teach6"):
        verdicts: dict[str, dict[str, str]] = {}
        with open(ROOT / "docs" / "results" / folder / "summary.csv", newline="") as f:
            for r in csv.DictReader(f):
                if r["condition"] != "none" and r["metric"] in primary:
                    verdicts.setdefault(r["condition"], {})[r["metric"]] = r["verdict"]
        for condition, v in verdicts.items():
            seen.add(condition)
            assert v["falls"] != "better" or "worse" in v.values(), (folder, condition, v)
    assert {"paper", "rescue-terminal", "warm-start-keep-shield-short"} <= seen


def test_the_pipeline_tunes_the_balance_preset_as_tune_does(tmp_path):
    """``pidlab run ENV --preset balance`` writes the coach ``pidlab tune ENV --auto --preset balance`` does."""
    from pidlab.controller.balance import tune_balance
    from pidlab.pipeline import _Session, _tune, settings_for
    from pidlab.plant.model import load_model

    loaded = load_model("Hopper-v5")
    settings = settings_for("Hopper-v5", preset="balance")
    session = _Session("Hopper-v5", tmp_path, settings, loaded, False, lambda _: None, [])
    spec, summary, path = _tune(session, None)  # the balance preset linearizes at its own posture
    assert path == tmp_path / "tuned.toml" and summary["preset"] == "balance"
    expected = tune_balance(loaded).spec
    assert [lp.actuators for lp in spec.loops] == [lp.actuators for lp in expected.loops]
    assert [lp.signal for lp in spec.loops] == [lp.signal for lp in expected.loops]
    assert spec.provenance["balance_posture_qpos"] == expected.provenance["balance_posture_qpos"]


@pytest.mark.parametrize("with_core", [True, False])
def test_the_rescue_paragraph_says_what_a_rescue_is_and_no_nan(with_core):
    """A coach certified by simulation (legged envs) has no core: the paragraph says held, not nan %."""
    from types import SimpleNamespace

    from pidlab.report.pipeline import _rescue

    coverage = {"rescuable": 1950, "samples": 2000, "rescue": 0.967, "takeover box": 0.533}
    if with_core:
        coverage["core"] = 0.25
    r = {"coverage": coverage, "validation": {"samples": 2000, "failures": 0, "rounds": 1, "failure_bound_95": 0.0015},
         "cells": [24, 24], "variables": ["rooty_pos", "rooty_vel"], "lower": [-0.2, -2.0], "upper": [0.2, 2.0],
         "guard": {}, "trigger": "predictive", "fraction_marked": 0.936, "horizon_s": 3.0}  # fmt: skip
    facts = SimpleNamespace(units={"rooty_pos": "rad", "rooty_vel": "rad/s"})
    text = "\n".join(_rescue(facts, r))
    assert "nan" not in text
    assert "the rescue region holds 96.7 % of them" in text and "the critical box 53.3 %" in text
    if with_core:
        assert "into its certified core" in text and "the certified core 25.0 %" in text
    else:
        assert (
            "holds the system 3 s without a termination" in text
            and "certified core" not in text.split("(")[-1]
        )
