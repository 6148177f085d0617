"""``pidlab init``: a user's MJCF scaffolded into a card, a recipe and an env module that work."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from pidlab.plant.card import load_card
from pidlab.plant.scaffold import module_name, scaffold, signal_names
from pidlab.rl.recipe import load_recipe
from tests.helpers import cli_in_process

DATA = Path(__file__).resolve().parent / "data"
XML = DATA / "cartpole" / "cartpole.xml"
ENV_ID = "ScaffoldCartPole-v0"
PIDLAB = str(Path(sys.executable).with_name("pidlab"))


def test_the_scaffold_names_every_joint_and_puts_the_unactuated_first():
    s = scaffold(XML, ENV_ID)
    assert s.module == module_name(ENV_ID) == "scaffoldcartpole_v0_env"
    assert set(s.files) == {f"models/{ENV_ID}.toml", f"coach/{ENV_ID}.toml", f"{s.module}.py", "pidlab.toml"}


def test_init_writes_files_that_train(tmp_path: Path) -> None:
    code, err = cli_in_process("init", str(XML), "--env-id", ENV_ID, "--out", str(tmp_path))
    assert code == 0, err
    card = load_card(tmp_path / "models" / f"{ENV_ID}.toml")
    assert card.operating_point.name == "keyframe upright"
    assert card.observation_names == ("pole_angle_pos", "cart_x_pos", "pole_angle_vel", "cart_x_vel")
    assert [(t.signal, t.low, t.high) for t in card.termination] == [("pole_angle_pos", -0.2, 0.2),
                                                                     ("cart_x_pos", -5.0, 5.0)]  # fmt: skip
    assert [(lp.name, lp.core) for lp in card.tuning] == [("pole_angle", True), ("cart_x", False)]
    assert load_recipe(tmp_path / "coach" / f"{ENV_ID}.toml").env_id == ENV_ID
    # the MJCF stays where it is (its includes and meshes keep working): the card names it
    assert not (tmp_path / "cartpole.xml").exists() and card.model is not None
    assert card.model.mjcf == str(XML) and card.model.frame_skip == 2
    # the project file makes the folder's commands find the env module, the card and the recipe
    env = {k: v for k, v in os.environ.items() if not k.startswith("PIDLAB_") and k != "PYTHONPATH"}
    for args in (["tune", ENV_ID, "--auto", "-o", "spec.toml"], ["bounds", "spec.toml", "--write", "--samples", "40"],
                 ["train", ENV_ID, "--coach", "spec.toml", "--steps", "600", "--no-progress"]):  # fmt: skip
        done = subprocess.run([PIDLAB, *args], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, done.stderr
    assert "completed" in done.stdout


def test_bad_init_is_one_line_and_exit_2(tmp_path: Path) -> None:
    bad = tmp_path / "no_actuator.xml"
    bad.write_text(XML.read_text().split("<actuator>")[0] + "</mujoco>\n")
    cases = [
        ([str(bad), "--env-id", ENV_ID], "has no actuator"),
        ([str(XML), "--env-id", ENV_ID, "--keyframe", "sideways"], "no keyframe 'sideways'; keyframes: upright"),
        ([str(XML), "--env-id", "../escape"], "--env-id"),
        ([str(tmp_path / "missing.xml"), "--env-id", ENV_ID], "does not exist"),
        ([str(XML), "--env-id", ENV_ID, "--out", str(bad)], "is a file, not a folder"),
    ]
    for args, message in cases:
        code, err = cli_in_process("init", *args, *([] if "--out" in args else ["--out", str(tmp_path / "out")]))
        assert code == 2 and message in err and "Traceback" not in err, (args, err)
        assert len(err.strip().splitlines()) == 1 and not (tmp_path / "out").exists()
    # no overwrite without --force, and nothing written then
    out = tmp_path / "again"
    assert cli_in_process("init", str(XML), "--env-id", ENV_ID, "--out", str(out))[0] == 0
    card = out / "models" / f"{ENV_ID}.toml"
    card.write_text(card.read_text().replace("low = -0.2", "low = -0.3"))
    code, err = cli_in_process("init", str(XML), "--env-id", ENV_ID, "--out", str(out))
    assert code == 2 and "exists" in err and "--force" in err
    assert "low = -0.3" in card.read_text()
    assert cli_in_process("init", str(XML), "--env-id", ENV_ID, "--out", str(out), "--force")[0] == 0
    assert "low = -0.3" not in card.read_text()
    shutil.rmtree(out)


@pytest.mark.parametrize("env_id", ["MyCartPole-v0", "robot.arm-v1"])
def test_module_names_are_python_names(env_id: str) -> None:
    assert module_name(env_id).isidentifier()


def test_joint_names_that_are_no_signal_names_get_signal_names_that_load(tmp_path: Path) -> None:
    odd = tmp_path / "odd.xml"
    odd.write_text(XML.read_text().replace('"pole_angle"', '"pole angle"').replace('"cart_x"', '"1cart.x"'))
    s = scaffold(odd, ENV_ID, out=tmp_path)
    (tmp_path / "models").mkdir()
    (tmp_path / "models" / f"{ENV_ID}.toml").write_text(s.files[f"models/{ENV_ID}.toml"])
    card = load_card(tmp_path / "models" / f"{ENV_ID}.toml")
    assert card.observation_names == ("pole_angle_pos", "1cart_x_pos", "pole_angle_vel", "1cart_x_vel")
    assert [v.joint for v in card.observation] == ["pole angle", "1cart.x", "pole angle", "1cart.x"]
    assert card.termination[0].signal == "pole angle_pos" and card.rescue is not None
    assert dict(card.rescue.guard) == {"1cart_x_pos": 0.5, "1cart_x_vel": 0.5}
    assert signal_names([("a b", True, False, None), ("a_b", True, False, None), ("_x", False, True, None)]) == {
        "a b": "a_b", "a_b": "a_b_1", "_x": "j_x"}  # fmt: skip
