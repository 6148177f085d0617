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
from tests.helpers import DATA, PAPER_ENVS


@pytest.fixture(scope="session", autouse=True)
def _sb3_logdir(tmp_path_factory: pytest.TempPathFactory) -> None:
    """Keep SB3's default log folder in pytest's temporary tree.

    A raw SB3 ``learn`` without a logger of its own creates ``$TMPDIR/SB3-<time>`` for every
    call (its ``configure`` makes the folder even when it writes nothing); pidlab's runs set
    their own logger, but tests that drive SB3 directly would litter the machine's temporary
    folder with empty folders.
    """
    os.environ.setdefault("SB3_LOGDIR", str(tmp_path_factory.mktemp("sb3")))


@pytest.fixture(scope="session")
def models() -> dict[str, LoadedModel]:
    return {env: load_model(env) for env in PAPER_ENVS}


@pytest.fixture(scope="session")
def data_dir() -> Path:
    return DATA
