"""The ``pidlab linearize`` command, as a user runs it: real processes, real output."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import PAPER_ENVS, cli_in_process

PIDLAB = [sys.executable, "-m", "pidlab"]


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*PIDLAB, *args], capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("env", PAPER_ENVS)
def test_linearize_json_on_paper_envs(env, models):
    res = run("linearize", env, "--json")
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout)
    nv = models[env].model.nv
    assert len(out["states"]) == 2 * nv
    assert len(out["continuous"]["A"]) == 2 * nv and len(out["continuous"]["A"][0]) == 2 * nv
    assert out["outputs"] == list(models[env].card.observation_names)
    assert out["discrete"]["dt"] == pytest.approx(models[env].control_dt)
    assert out["continuous"]["controllability_rank"] == 2 * nv
    assert sum(out["continuous"]["unstable"]) >= 1  # every paper env is open-loop unstable here


def test_linearize_table_marks_unstable_and_ranks():
    res = run("linearize", "InvertedPendulum-v5")
    assert res.returncode == 0, res.stderr
    assert "UNSTABLE" in res.stdout
    assert "controllability rank: 4 / 4" in res.stdout
    assert "hinge_vel" in res.stdout and "slide" in res.stdout
    disc = run("linearize", "InvertedPendulum-v5", "--discrete")
    assert "dt = 0.04 s" in disc.stdout and "|z|" in disc.stdout


def test_linearize_mjcf_with_keyframe_and_explicit_point(data_dir: Path):
    xml = str(data_dir / "floating_arm.xml")
    res = run("linearize", xml, "--at", "bent", "--json")
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout)
    assert out["operating_point"]["source"] == "keyframe:bent"
    assert len(out["states"]) == 22
    res = run(
        "linearize", "InvertedPendulum-v5", "--at", "qpos0", "--qvel", "0.1,0", "--equilibrium-ctrl", "--json"
    )
    out = json.loads(res.stdout)
    assert out["operating_point"]["source"] == "qpos0+explicit qvel"
    assert out["operating_point"]["ctrl_source"] == "inverse dynamics"


def test_settle_finds_the_standing_point_from_qpos0(models):
    res = run("linearize", "Hopper-v5", "--at", "qpos0", "--settle", "rootz,rooty", "--json")
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout)
    assert out["operating_point"]["source"] == "qpos0+settled rootz/rooty"
    assert out["operating_point"]["ctrl_source"] == "inverse dynamics"
    assert out["equilibrium_error"] < 1e-8  # qpos0 itself hovers and falls
    card_qpos = models["Hopper-v5"].card.operating_point.qpos
    assert out["operating_point"]["qpos"] == pytest.approx(list(card_qpos), abs=1e-6)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["NoSuchEnv-v5"], "unknown env id or missing file 'NoSuchEnv-v5'"),
        (["Hopper-v9"], "did you mean Hopper-v5"),
        (["CartPole-v1"], "not a MuJoCo env"),
        (["missing.xml"], "does not exist"),
        (["InvertedPendulum-v5", "--at", "upright"], "no keyframe 'upright'"),
        (
            ["InvertedPendulum-v5", "--qpos", "0,0,0"],
            "qpos has 3 entries; the model expects 2 (slider, hinge)",
        ),
        (["InvertedPendulum-v5", "--qpos", "a,b"], "expected comma-separated numbers"),
        (["InvertedPendulum-v5", "--discretization", "tustin"], "expected 'step' or 'zoh'"),
        (["InvertedPendulum-v5", "--eps", "0"], "expected a positive step"),
        (["Hopper-v5", "--settle", "knee"], "no joint 'knee' to settle; joints: rootx"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(args, message):
    res = run("linearize", *args)
    assert res.returncode == 2
    assert "Traceback" not in res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, res.stderr
    assert message in lines[0]


def test_broken_mjcf_shows_mujocos_message(tmp_path):
    bad = tmp_path / "broken.xml"
    bad.write_text("<mujoco><worldbody><body><joint type='hinge'/><geom type='box' size='1'/>")
    res = run("linearize", str(bad))
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert "MuJoCo could not compile" in res.stderr and "XML" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1


def test_non_finite_jacobian_exit_2(tmp_path):
    stiff = tmp_path / "stiff.xml"
    stiff.write_text(
        "<mujoco><worldbody><body><joint name='s' type='slide' stiffness='1e308'/>"
        "<geom type='sphere' size='0.1'/></body></worldbody></mujoco>"
    )
    res = run("linearize", str(stiff), "--qpos", "10")
    assert res.returncode == 2 and "not finite" in res.stderr


def test_version_and_help():
    assert run("--version").stdout.startswith("pidlab ")
    help_text = run("linearize", "--help").stdout
    assert "ENV_OR_MJCF" in help_text and "--equilibrium-ctrl" in help_text


@pytest.mark.parametrize(
    ("call", "library", "cli"),
    [
        (
            lambda: _check_port(0),
            "port=0: expected a TCP port",
            "--port 0: expected a TCP port",
        ),
        (
            lambda: _select(["none", "telepathy"]),
            "condition_names='none,telepathy': unknown condition(s) telepathy;",
            "--conditions 'none,telepathy': unknown condition(s) telepathy;",
        ),
        (
            lambda: _resolve("arm.xml", "card"),
            "at='card': arm.xml has no model card; expected qpos0 or a keyframe name",
            "--at 'card': arm.xml has no model card",
        ),
    ],
)
def test_library_names_parameters_the_cli_names_flags(call, library, cli, tmp_path, monkeypatch):
    """A Python caller reads its own parameter; the command line maps it to the flag it gave."""
    from pidlab.cli.main import cli_message
    from pidlab.errors import PidlabError

    monkeypatch.chdir(tmp_path)
    (tmp_path / "arm.xml").write_text(
        "<mujoco><worldbody><body><joint name='j' type='hinge'/><geom type='sphere' size='0.1'/>"
        "</body></worldbody><actuator><motor joint='j'/></actuator></mujoco>"
    )
    with pytest.raises(PidlabError) as err:
        call()
    assert str(err.value).startswith(library) and "--" not in str(err.value)
    assert cli_message(err.value).startswith(cli)


def _check_port(port):
    from pidlab.app.serve import check_port

    check_port(port)


def _select(names):
    from pidlab.experiment.conditions import load_conditions, select

    return select(load_conditions(), names, "coach/conditions.toml")


def _resolve(target, at):
    from pidlab.plant.model import load_model
    from pidlab.plant.operating_point import resolve_operating_point

    return resolve_operating_point(load_model(target), at)


def _chain(path: Path, joints: int) -> Path:
    """An MJCF model of ``joints`` pendulums side by side (2 * joints states, one motor)."""
    bodies = "".join(
        f'<body name="b{i}" pos="{0.05 * i} 0 0"><joint name="j{i}" type="hinge" axis="0 1 0"/>'
        '<geom type="capsule" fromto="0 0 0 0 0 -0.1" size="0.01"/></body>'
        for i in range(joints)
    )
    path.write_text(f'<mujoco><worldbody>{bodies}</worldbody><actuator><motor joint="j0"/></actuator></mujoco>')
    return path


def test_usage_errors_are_one_line_in_the_real_executable():
    """Click's usage box becomes one line, exit 2, in the installed ``pidlab`` too."""
    exe = Path(sys.executable).parent / "pidlab"
    cmd = [str(exe)] if exe.exists() else PIDLAB
    res = subprocess.run([*cmd, "linearize", "InvertedPendulum-v5", "--eps", "tiny"],
                         capture_output=True, text=True, timeout=120)  # fmt: skip
    assert res.returncode == 2
    assert res.stderr.splitlines() == [
        "pidlab: error: --eps 'tiny': expected a number (see 'pidlab linearize --help')"
    ]


@pytest.mark.parametrize(
    ("args", "line"),
    [
        (["train", "X", "--steps", "lots"], "--steps 'lots': expected an integer (see 'pidlab train --help')"),
        (["roa"], "missing argument 'SPEC' (see 'pidlab roa --help')"),
        (["roa", "x.toml", "--sampels", "3"], "no such option: --sampels"),
        (["frob"], "no such command 'frob'"),
    ],
)
def test_usage_errors_are_one_line_in_process(args, line):
    code, stderr = cli_in_process(*args)
    assert code == 2
    lines = stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"pidlab: error: {line}"), stderr


def test_linearize_refuses_a_model_too_large_to_analyze(tmp_path):
    from pidlab.cli.main import MAX_LINEARIZE_STATES

    xml = _chain(tmp_path / "chain.xml", MAX_LINEARIZE_STATES // 2 + 1)
    code, stderr = cli_in_process("linearize", str(xml))
    assert code == 2 and len(stderr.splitlines()) == 1, stderr
    assert f"{MAX_LINEARIZE_STATES + 2} states (2 nv + na) is more than pidlab linearize analyzes" in stderr


def test_linearize_says_first_how_long_a_large_model_takes(tmp_path, monkeypatch):
    import pidlab.linear.linearize as lin

    monkeypatch.setattr(lin, "estimate_seconds", lambda loaded, discretization: 1500.0)
    code, stderr = cli_in_process("linearize", str(_chain(tmp_path / "chain.xml", 3)))
    assert code == 0
    assert stderr.splitlines() == [
        "pidlab: chain.xml has 6 states: linearizing and analyzing it takes about 25 min (--progress shows a bar)"
    ]


def test_linearize_progress_bars_and_estimate(tmp_path):
    from pidlab.linear.linearize import estimate_seconds, finite_difference_columns, linearize
    from pidlab.plant.model import load_model

    loaded = load_model(_chain(tmp_path / "chain.xml", 40))
    seen = []
    linearize(loaded, progress=lambda done, total: seen.append((done, total)))
    total = finite_difference_columns(loaded)
    assert total == 2 * (80 + 1) and seen[-1] == (total, total) and len(seen) == total
    assert 0 < estimate_seconds(loaded, analysis=False) < float("inf") and estimate_seconds(loaded) > 0
    code, stderr = cli_in_process("linearize", str(tmp_path / "chain.xml"), "--progress")
    assert code == 0 and "finite differences" in stderr and "modes of the discrete model" in stderr


def test_linearize_names_a_large_matrix_instead_of_printing_it():
    import numpy as np
    from rich.console import Console

    from pidlab.report.console import MAX_TABLE_SIDE, matrix_table

    names = [f"s{i}" for i in range(MAX_TABLE_SIDE + 1)]
    con = Console(width=200, record=True)
    con.print(matrix_table("A", np.zeros((len(names), len(names))), names, names))
    assert f"{len(names)} x {len(names)}: more than {MAX_TABLE_SIDE}" in con.export_text()


def test_a_model_that_loads_passes_mujocos_warnings_on_and_one_that_fails_does_not(tmp_path, capfd):
    from pidlab.errors import ModelCompileError
    from pidlab.plant.model import load_model

    with pytest.raises(ModelCompileError, match="is a folder"):
        load_model(tmp_path)
    assert "2GB" not in capfd.readouterr().err  # MuJoCo's own warning about a folder is not printed


def _help_texts() -> list[tuple[str, str]]:
    """Every command's name and help texts (its own, its parameters'), as the source writes them."""
    import typer

    from pidlab.cli import app

    group = typer.main.get_command(app)
    out = []
    for name, command in group.commands.items():
        texts = [command.help or ""] + [getattr(p, "help", None) or "" for p in command.params]
        out.append((name, [t.split("\f")[0] for t in texts if t]))
    return out


@pytest.mark.parametrize("name,texts", _help_texts(), ids=[n for n, _ in _help_texts()])
def test_help_shows_every_text_whole(name: str, texts: list[str]) -> None:
    """A TOML table in a help text ("Kept in [bounds.forecast]") is shown, not dropped as rich markup."""
    import re

    from typer.testing import CliRunner

    from pidlab.cli import app

    result = CliRunner().invoke(app, [name, "--help"], terminal_width=200, env={"COLUMNS": "200"})
    assert result.exit_code == 0
    shown = re.sub(r"[\s│]", "", result.stdout)
    for text in texts:
        for token in re.findall(r"\[[^\]\n]*\]|<[^>\n]*>", text):
            assert re.sub(r"\s", "", token) in shown, f"{name}: {token} missing from its --help"


def test_a_path_that_reads_as_rich_markup_is_printed_as_written(tmp_path) -> None:
    """A folder named ``x[/y]`` is a path, not a closing tag: printed whole, no traceback."""
    from typer.testing import CliRunner

    from pidlab.cli import app
    from tests.helpers import TUNING

    folder = tmp_path / "x[" / "y]"
    folder.mkdir(parents=True)
    spec = folder / "InvertedPendulum-v5.mine.toml"
    spec.write_text((TUNING / "InvertedPendulum-v5.pidlab-rescue.toml").read_text())
    result = CliRunner().invoke(
        app, ["rescue-coverage", str(spec), "--domain", "hinge_pos=0.1", "--states", "20", "--workers", "1"],
        terminal_width=400, env={"COLUMNS": "400"},
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    assert f"{folder}/.{spec.name}.coverage-labels" in result.stdout


def test_a_progress_description_is_shown_as_written() -> None:
    import io

    from rich.console import Console

    from pidlab.report.console import progress_bar

    out = io.StringIO()
    with progress_bar(Console(file=out, force_terminal=True, width=120)) as bar:
        bar.add_task("coverage of x[/y] and [bold]", total=1.0)
    assert "coverage of x[/y] and [bold]" in out.getvalue()
