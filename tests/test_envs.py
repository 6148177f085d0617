"""Your own env: ``module:EnvId``, ``--gym-packages`` / ``PIDLAB_GYM_PACKAGES``, MuJoCo envs known by what they are."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from pidlab.cli import app
from pidlab.plant.envs import GYM_PACKAGES_VAR, is_mujoco_env, make_env, resolve_env_id
from pidlab.plant.model import load_model

PIDLAB = str(Path(sys.executable).with_name("pidlab"))

# "mujoco" is in no entry point of a MuJoCo env here, and in one of a classic-control env
ROBOTS = '''
import gymnasium as gym
from gymnasium.envs.mujoco.inverted_pendulum_v5 import InvertedPendulumEnv


class MyPendulum(InvertedPendulumEnv):
    """A user's MuJoCo env (here the shipped pendulum under another name)."""


gym.register("MyPendulum-v0", entry_point="my_robots:MyPendulum", max_episode_steps=1000)
'''
FAKE = '''
import gymnasium as gym
from gymnasium.envs.classic_control.cartpole import CartPoleEnv


class NotMujoco(CartPoleEnv):
    """A classic-control env in a module whose name says mujoco."""


gym.register("FakeMujoco-v0", entry_point="fake_mujoco_envs:NotMujoco")
'''


@pytest.fixture
def robots(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A folder on sys.path with the user's module ``my_robots`` and ``fake_mujoco_envs``."""
    (tmp_path / "my_robots.py").write_text(ROBOTS)
    (tmp_path / "fake_mujoco_envs.py").write_text(FAKE)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv(GYM_PACKAGES_VAR, "")  # restored after the test, whatever the test adds
    return tmp_path


def _cli(*args: str) -> tuple[int, str, str]:
    result = CliRunner().invoke(app, list(args))
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        raise result.exception
    return result.exit_code, result.stdout, result.stderr


def test_module_colon_env_id_imports_the_module_and_names_the_env(robots: Path) -> None:
    loaded = load_model("my_robots:MyPendulum-v0")
    assert loaded.env_id == "MyPendulum-v0" and loaded.model.nu == 1
    assert resolve_env_id("MyPendulum-v0") == "MyPendulum-v0"  # registered from now on
    code, out, err = _cli("linearize", "my_robots:MyPendulum-v0", "--json")
    assert code == 0, err
    assert json.loads(out)["states"][:2] == ["slider_pos", "hinge_pos"]
    # a command that starts processes passes the module on (they import it too)
    code, _, err = _cli("train", "my_robots:MyPendulum-v0", "--coach", "none")
    assert code == 2 and "MyPendulum-v0" in err  # no recipe for it
    assert os.environ[GYM_PACKAGES_VAR] == "my_robots"


def test_gym_packages_and_its_variable_register_envs_here_and_in_child_processes(robots: Path) -> None:
    code, _, err = _cli("--gym-packages", "my_robots", "linearize", "MyPendulum-v0", "--json")
    assert code == 0, err
    env = {**os.environ, GYM_PACKAGES_VAR: "my_robots", "PYTHONPATH": str(robots)}
    child = "from pidlab.plant.envs import make_env; e = make_env('MyPendulum-v0'); print(type(e.unwrapped).__name__)"
    done = subprocess.run([sys.executable, "-c", child], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout.strip() == "MyPendulum", done.stderr


def test_a_mujoco_env_is_known_by_what_it_is_not_by_its_entry_point(robots: Path) -> None:
    assert is_mujoco_env(make_env("my_robots:MyPendulum-v0"))
    env = make_env("fake_mujoco_envs:FakeMujoco-v0")
    assert not is_mujoco_env(env)
    code, _, err = _cli("linearize", "FakeMujoco-v0")
    assert code == 2 and "not a MuJoCo env" in err and "NotMujoco" in err, err


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--gym-packages", "no_such_module_here", "linearize", "MyPendulum-v0"], "cannot import 'no_such_module_here'"),
        (["--gym-packages", "my robots", "linearize", "MyPendulum-v0"], "is not a module name"),
        (["linearize", "my_robots:"], "no env id after the module"),
        (["linearize", "no_such_module_here:X-v0"], "cannot import 'no_such_module_here'"),
        (["train", "no_such_module_here:X-v0", "--coach", "none"], "cannot import 'no_such_module_here'"),
        (["linearize", "Unregistered-v0"], "pidlab --gym-packages MODULE"),
    ],
)
def test_bad_modules_are_one_line_and_exit_2(robots: Path, args: list[str], message: str) -> None:
    code, _, err = _cli(*args)
    assert code == 2 and message in err and "Traceback" not in err, err
    assert len(err.strip().splitlines()) == 1, err


def test_the_installed_command_imports_the_users_module(robots: Path, tmp_path: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(robots)}
    done = subprocess.run([PIDLAB, "--gym-packages", "my_robots", "linearize", "MyPendulum-v0", "--json"],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "hinge_pos" in done.stdout
