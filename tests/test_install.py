"""A regular (non-editable) install, run from another folder, finds the shipped cards, specs and recipes.

The wheel is built from a copy of the tracked files (nothing is written into the checkout) and
installed into a fresh venv whose only view of the dependencies is a ``.pth`` line naming this
environment's site-packages (no download, no second torch). Every check runs in a folder that is
neither the checkout nor the venv, with the ``PIDLAB_*`` overrides unset.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

from tests.helpers import ROOT

CHECK = """
import pathlib, sys
import pidlab
from pidlab.data import coach_dir, models_dir, source_root, tuning_dir
from pidlab.plant.card import find_card
from pidlab.controller.spec import load_spec
from pidlab.rl.recipe import default_recipe_path, load_recipe, recipe_envs
from pidlab.experiment.sweep import plan

installed = pathlib.Path(pidlab.__file__).resolve().parent
assert installed.is_relative_to(pathlib.Path(sys.prefix).resolve()), installed
assert source_root() is None, source_root()
for folder in (models_dir(), tuning_dir(), coach_dir()):
    assert folder.is_relative_to(installed), folder
envs = recipe_envs()
assert envs == ["Hopper-v5", "InvertedDoublePendulum-v5", "InvertedPendulum-v5", "Walker2d-v5"], envs
for env in envs:
    card = find_card(env)
    assert card is not None and card.tuning and card.paper is not None, env
    load_recipe(default_recipe_path(env))
    for name in ("paper", "pidlab-robust", "pidlab-weak"):
        assert load_spec(tuning_dir() / f"{env}.{name}.toml").env_id == env
p = plan(["InvertedPendulum-v5"], ["none", "paper", "pidlab"], [0], "exp")
assert len(p.tasks) == 3 and not pathlib.Path("exp").exists()
print("ok", len(envs))
"""


def _site_packages(venv: Path) -> Path:
    found = sorted(venv.glob("lib/python*/site-packages"))
    assert found, f"no site-packages in {venv}"
    return found[0]


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A venv with pidlab installed from a wheel built off the tracked files."""
    work = tmp_path_factory.mktemp("install")
    src = work / "src"
    tracked = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard"], cwd=ROOT, capture_output=True, text=True, check=True)
    for rel in tracked.stdout.splitlines():
        if rel.startswith(("docs/", "tests/", "benchmarks/")) or not (ROOT / rel).is_file():
            continue
        (src / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / rel, src / rel)
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q"]
    subprocess.run([*pip, "wheel", "--no-deps", "--no-build-isolation", "-w", str(work / "dist"), str(src)],
                   check=True, capture_output=True, text=True)  # fmt: skip
    wheel = next((work / "dist").glob("pidlab-*.whl"))
    venv = work / "venv"
    base = getattr(sys, "_base_executable", sys.executable)
    subprocess.run([base, "-m", "venv", str(venv)], check=True)
    here = Path(sysconfig.get_paths()["purelib"])
    (_site_packages(venv) / "zz_dependencies.pth").write_text(f"{here}\n")
    subprocess.run([str(venv / "bin" / "python"), "-m", "pip", "install", "-q", "--no-deps", "--no-index",
                    str(wheel)], check=True, capture_output=True, text=True)  # fmt: skip
    return venv


def _clean_env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if not k.startswith("PIDLAB_") and k != "PYTHONPATH"}


def test_the_wheel_ships_the_data_folders(installed: Path) -> None:
    data = _site_packages(installed) / "pidlab" / "_data"
    for name in ("models", "tuning", "coach"):
        shipped = sorted(p.name for p in (data / name).glob("*.toml"))
        assert shipped == sorted(p.name for p in (ROOT / name).glob("*.toml")), name


def test_an_installed_copy_finds_cards_specs_and_recipes_from_another_folder(installed: Path, tmp_path: Path) -> None:
    done = subprocess.run([str(installed / "bin" / "python"), "-c", CHECK], cwd=tmp_path, env=_clean_env(),
                          capture_output=True, text=True, timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "ok 4"


def test_the_installed_command_line_runs_from_another_folder(installed: Path, tmp_path: Path) -> None:
    done = subprocess.run([str(installed / "bin" / "pidlab"), "linearize", "InvertedPendulum-v5", "--json"],
                          cwd=tmp_path, env=_clean_env(), capture_output=True, text=True, timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert '"hinge_pos"' in done.stdout and not list(tmp_path.iterdir())


LAYERS = """
from pidlab.plant.card import find_card
from pidlab.experiment.conditions import conditions_path, load_conditions, spec_path
from pidlab.rl.recipe import default_recipe_path, recipe_envs
print(find_card("InvertedPendulum-v5").path, find_card("Hopper-v5").path, find_card("Nope-v0"))
print(default_recipe_path("InvertedPendulum-v5"), default_recipe_path("Hopper-v5"), conditions_path())
print(spec_path("InvertedPendulum-v5", "paper"), spec_path("Hopper-v5", "paper"))
print(" ".join(recipe_envs()), "rescue-terminal" in load_conditions())
"""


def test_an_environment_variable_adds_a_folder_in_front_of_the_shipped_one(installed: Path, tmp_path: Path) -> None:
    """A user's folder holds only their files: the shipped cards, recipes, specs and conditions stay found."""
    folders = {name: tmp_path / name for name in ("models", "tuning", "coach")}
    for f in folders.values():
        f.mkdir()
    shutil.copy2(ROOT / "models" / "InvertedPendulum-v5.toml", folders["models"] / "InvertedPendulum-v5.toml")
    shutil.copy2(ROOT / "coach" / "InvertedPendulum-v5.toml", folders["coach"] / "InvertedPendulum-v5.toml")
    shutil.copy2(ROOT / "coach" / "InvertedPendulum-v5.toml", folders["coach"] / "MyRobot-v0.toml")
    shutil.copy2(ROOT / "tuning" / "InvertedPendulum-v5.paper.toml", folders["tuning"] / "InvertedPendulum-v5.paper.toml")
    env = {**_clean_env(), **{f"PIDLAB_{name.upper()}": str(f) for name, f in folders.items()}}
    done = subprocess.run([str(installed / "bin" / "python"), "-c", LAYERS], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr
    cards, recipes, specs, listing = done.stdout.strip().splitlines()
    shipped = _site_packages(installed) / "pidlab" / "_data"
    assert cards.split() == [str(folders["models"] / "InvertedPendulum-v5.toml"),
                             str(shipped / "models" / "Hopper-v5.toml"), "None"]  # fmt: skip
    assert recipes.split() == [str(folders["coach"] / "InvertedPendulum-v5.toml"),
                               str(shipped / "coach" / "Hopper-v5.toml"), str(shipped / "coach" / "conditions.toml")]  # fmt: skip
    assert specs.split() == [str(folders["tuning"] / "InvertedPendulum-v5.paper.toml"),
                             str(shipped / "tuning" / "Hopper-v5.paper.toml")]  # fmt: skip
    assert listing == ("Hopper-v5 InvertedDoublePendulum-v5 InvertedPendulum-v5 MyRobot-v0 Walker2d-v5 True")
