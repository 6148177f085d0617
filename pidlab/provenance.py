"""Provenance: what a run, an experiment or a pipeline records so that it can be reproduced."""

from __future__ import annotations

import platform
import subprocess
import sys
from importlib import metadata
from pathlib import Path
from typing import Any

PACKAGES = (
    "pidlab",
    "numpy",
    "scipy",
    "torch",
    "stable-baselines3",
    "gymnasium",
    "mujoco",
    "control",
    "casadi",
    "tensorboard",
)


def package_versions() -> dict[str, str]:
    """Versions of Python, the platform and the packages a run depends on."""
    out = {"python": sys.version.split()[0], "platform": platform.platform()}
    for name in PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


def git_state(folder: str | Path | None = None) -> dict[str, Any]:
    """The git commit of pidlab's source tree and whether it has uncommitted changes.

    Returns ``{"sha": None, ...}`` outside a git checkout.
    """
    folder = Path(folder) if folder else Path(__file__).resolve().parents[1]

    def git(*args: str) -> str | None:
        try:
            done = subprocess.run(
                ["git", *args], cwd=folder, capture_output=True, text=True, timeout=10, check=False
            )
        except (OSError, subprocess.SubprocessError):
            return None
        return done.stdout.strip() if done.returncode == 0 else None

    sha = git("rev-parse", "HEAD")
    status = git("status", "--porcelain", "--untracked-files=no") if sha else None
    return {"sha": sha, "dirty": bool(status) if status is not None else None}
