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


@pytest.fixture(scope="session")
def models() -> dict[str, LoadedModel]:
    return {env: load_model(env) for env in PAPER_ENVS}


@pytest.fixture(scope="session")
def data_dir() -> Path:
    return DATA
