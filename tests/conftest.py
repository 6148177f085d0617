"""Shared fixtures: models are loaded once per session (loading a Gymnasium env costs ~50 ms)."""

from __future__ import annotations

from pathlib import Path

import pytest

from pidlab.model import LoadedModel, load_model

PAPER_ENVS = ("InvertedPendulum-v5", "InvertedDoublePendulum-v5", "Hopper-v5", "Walker2d-v5")
DATA = Path(__file__).parent / "data"


@pytest.fixture(scope="session")
def models() -> dict[str, LoadedModel]:
    return {env: load_model(env) for env in PAPER_ENVS}


@pytest.fixture(scope="session")
def data_dir() -> Path:
    return DATA
