"""Helpers shared by the tests: the repository's folders and the in-process command line.

Fixtures live in ``conftest.py``; everything a test imports lives here (no test imports from
``conftest``).
"""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
"""The checkout."""
TUNING = ROOT / "tuning"
MODELS = ROOT / "models"
COACH = ROOT / "coach"
DATA = Path(__file__).resolve().parent / "data"
"""Test data: MJCF files and the bad-input corpus."""
PAPER_ENVS = ("InvertedPendulum-v5", "InvertedDoublePendulum-v5", "Hopper-v5", "Walker2d-v5")


def benchmark(name: str):
    """The module ``benchmarks/NAME.py``, imported as its scripts import each other (their folder on ``sys.path``).

    Whatever the order the tests run in: a script imports its siblings (``bench_cli``) by name.
    """
    import importlib
    import sys

    folder = str(ROOT / "benchmarks")
    if folder not in sys.path:
        sys.path.insert(0, folder)
    return importlib.import_module(name)


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


SHIELD = {"mode": "takeover", "region": "rescue", "trigger": "predictive", "handback": 0.5, "view": "terminal"}
"""The rescue-terminal shield as ``[coaching]`` fields (the off-policy couplings' tests)."""


def sac_recipe_data(**coaching: object) -> dict:
    """The shipped InvertedPendulum recipe as a table: SAC on a small network, a few hundred env steps,
    behind the rescue-terminal shield, with ``coaching`` fields added."""
    import tomllib

    data = tomllib.loads((COACH / "InvertedPendulum-v5.toml").read_text())
    data.update(algo="sac", steps=400, evaluation={"every": 200, "episodes": 2, "seed": 123},
                checkpoint={"every": 200})  # fmt: skip
    data["sac"].update(learning_starts=100, buffer_size=2000, batch_size=16, train_freq=8, gradient_steps=8,
                       policy_kwargs={"net_arch": [16, 16], "log_std_init": -3.0})  # fmt: skip
    data["coaching"] = {**SHIELD, **coaching}
    return data


def changed_recipe(recipe: object, change: dict) -> object:
    """``recipe`` with top-level fields replaced, or with ``change["coaching"]`` fields added."""
    import dataclasses

    from pidlab.rl.recipe import parse_coaching, recipe_to_dict

    if "coaching" in change:
        fields = {**recipe_to_dict(recipe)["coaching"], **change["coaching"]}  # type: ignore[arg-type]
        return dataclasses.replace(recipe, coaching=parse_coaching(fields))  # type: ignore[type-var]
    return dataclasses.replace(recipe, **change)  # type: ignore[type-var]
