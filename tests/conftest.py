"""Shared fixtures: models are loaded once per session (loading a Gymnasium env costs ~50 ms)."""

from __future__ import annotations

import ctypes.util
import os

# MuJoCo picks its OpenGL backend when it is first imported: headless offscreen rendering (the
# tuner's rollout animation, tests/test_animation.py) needs EGL, which scripts/browser.sh installs
if not os.environ.get("DISPLAY") and ctypes.util.find_library("EGL"):
    os.environ.setdefault("MUJOCO_GL", "egl")

from pathlib import Path

import pytest

from pidlab.plant.model import LoadedModel, load_model

PAPER_ENVS = ("InvertedPendulum-v5", "InvertedDoublePendulum-v5", "Hopper-v5", "Walker2d-v5")
DATA = Path(__file__).parent / "data"


@pytest.fixture(scope="session")
def models() -> dict[str, LoadedModel]:
    return {env: load_model(env) for env in PAPER_ENVS}


@pytest.fixture(scope="session")
def data_dir() -> Path:
    return DATA


def cli_in_process(*args: str) -> tuple[int, str]:
    """Run the ``pidlab`` command line in this process: (exit code, stderr).

    The parametrized bad-input tests use it (a subprocess costs ~5 s of imports each); one
    case per verb still runs the real ``pidlab`` executable.
    """
    from typer.testing import CliRunner

    from pidlab.cli import app

    result = CliRunner().invoke(app, list(args))
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        raise result.exception
    return result.exit_code, result.stderr
