"""The project file ``pidlab.toml``, and a robot with a model card and no env (its ``[model]`` table)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from pidlab.errors import ModelCardError, ProjectError, UnknownEnvError
from pidlab.plant.card import load_card
from pidlab.plant.envs import GYM_PACKAGES_VAR, check_trainable, make_coach_env
from pidlab.plant.model import load_model
from pidlab.plant.scaffold import scaffold
from pidlab.project import apply_project, find_project, load_project
from tests.helpers import cli_in_process
from tests.test_docs_commands import serve_ui

XML = Path(__file__).resolve().parent / "data" / "cartpole" / "cartpole.xml"
PIDLAB = str(Path(sys.executable).with_name("pidlab"))
PREVIEW = """
import gymnasium
from pidlab.app.jobs import rollout_preview
from pidlab.controller.spec import load_spec
p = rollout_preview(load_spec("tuning/BareCartPole-v0.pidlab-robust.toml"), episodes=2)
print(p.episodes, p.mean_length, "BareCartPole-v0" in gymnasium.registry)
"""
VARIABLES = ("PIDLAB_MODELS", "PIDLAB_TUNING", "PIDLAB_COACH", GYM_PACKAGES_VAR, "PIDLAB_PROJECT", "PYTHONPATH")


@pytest.fixture
def clean_env(monkeypatch: pytest.MonkeyPatch) -> pytest.MonkeyPatch:
    """The variables a project sets, unset now and restored after the test; ``sys.path`` too."""
    for name in VARIABLES:
        monkeypatch.setenv(name, "")  # recorded, so the test's changes are undone
        monkeypatch.delenv(name)
    monkeypatch.setattr(sys, "path", list(sys.path))
    return monkeypatch


def _card_only(folder: Path, env_id: str = "CardOnlyCartPole-v0") -> Path:
    """A folder with the cart-pole MJCF and its scaffolded card (no env module, no project file)."""
    (folder / "models").mkdir(parents=True)
    (folder / "cartpole.xml").write_text(XML.read_text())
    s = scaffold(folder / "cartpole.xml", env_id, out=folder)
    (folder / "models" / f"{env_id}.toml").write_text(s.files[f"models/{env_id}.toml"])
    return folder / "models" / f"{env_id}.toml"


def test_a_project_sets_folders_modules_and_the_search_path(tmp_path: Path, clean_env) -> None:
    (tmp_path / "cards").mkdir()
    (tmp_path / "pidlab.toml").write_text(
        'schema = "pidlab.project/1"\ngym_packages = ["robots_here"]\nmodels = "cards"\ncoach = "recipes"\n'
    )
    assert find_project(tmp_path) == tmp_path / "pidlab.toml" and find_project(tmp_path / "cards") is None
    project = load_project(tmp_path / "pidlab.toml")
    assert project.gym_packages == ("robots_here",)
    assert dict(project.folders) == {"models": tmp_path / "cards", "coach": tmp_path / "recipes"}
    clean_env.setenv("PIDLAB_COACH", "/somewhere/mine")  # set by the user: it wins
    apply_project(project)
    assert os.environ["PIDLAB_MODELS"] == str(tmp_path / "cards")
    assert os.environ["PIDLAB_COACH"] == "/somewhere/mine" and "PIDLAB_TUNING" not in os.environ
    assert os.environ[GYM_PACKAGES_VAR] == "robots_here"
    assert sys.path[-1] == str(tmp_path) and os.environ["PIDLAB_PROJECT"] == str(tmp_path)
    assert "PYTHONPATH" not in os.environ  # children find the folder by PIDLAB_PROJECT, at the end
    apply_project(project)  # twice: nothing repeated
    assert os.environ[GYM_PACKAGES_VAR] == "robots_here" and sys.path.count(str(tmp_path)) == 1


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("schema = 1\n", "expected 'pidlab.project/1'"),
        ('schema = "pidlab.project/1"\nmodel = "m"\n', "unknown field(s) ['model']"),
        ('schema = "pidlab.project/1"\ngym_packages = "robots"\n', "expected a list of module names"),
        ('schema = "pidlab.project/1"\ngym_packages = ["../x"]\n', "expected a list of module names"),
        ('schema = "pidlab.project/1"\nmodels = ""\n', "models"),
        ('schema = "pidlab.project/1"\ntuning = "pidlab.toml"\n', "is a file; expected a folder"),
        ("schema = [\n", "pidlab.toml"),
    ],
)
def test_a_bad_project_file_is_one_line_and_exit_2(
    tmp_path: Path, text: str, message: str, clean_env
) -> None:
    (tmp_path / "pidlab.toml").write_text(text)
    with pytest.raises(ProjectError, match=None) as caught:
        load_project(tmp_path / "pidlab.toml")
    assert message in str(caught.value) and "\n" not in str(caught.value)
    clean_env.chdir(tmp_path)
    code, err = cli_in_process("linearize", "InvertedPendulum-v5")
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1


def test_a_project_folder_that_is_a_folder_is_refused(tmp_path: Path, clean_env) -> None:
    (tmp_path / "pidlab.toml").mkdir()
    clean_env.chdir(tmp_path)
    code, err = cli_in_process("linearize", "InvertedPendulum-v5")
    assert code == 2 and "pidlab.toml" in err and len(err.strip().splitlines()) == 1


def test_a_card_names_its_mjcf_and_the_control_stages_run_on_it(tmp_path: Path, clean_env) -> None:
    card_path = _card_only(tmp_path)
    card = load_card(card_path)
    assert card.model is not None and card.model.mjcf == str(tmp_path / "cartpole.xml")
    assert (card.model.frame_skip, card.model.max_episode_steps) == (2, 1000)  # 2 x 10 ms: the 20 ms period
    clean_env.setenv("PIDLAB_MODELS", str(tmp_path / "models"))
    by_file, by_id = load_model(tmp_path / "cartpole.xml"), load_model("CardOnlyCartPole-v0")
    for loaded in (by_file, by_id):
        assert loaded.env_id == "CardOnlyCartPole-v0" and loaded.frame_skip == 2 and loaded.card == card
    env = make_coach_env("CardOnlyCartPole-v0")
    try:
        obs, _ = env.reset(seed=0)
        assert obs.shape == (4,)
        steps = 0
        truncated = terminated = False
        while not (terminated or truncated):
            obs, reward, terminated, truncated, _ = env.step(env.action_space.sample() * 0)
            steps += 1
        assert terminated and reward == 0.0 and steps < 1000  # unactuated, the pole falls past 0.2 rad
    finally:
        env.close()
    for target in ("CardOnlyCartPole-v0", str(tmp_path / "cartpole.xml")):
        with pytest.raises(UnknownEnvError, match="pidlab init"):
            check_trainable(target)


def test_a_card_with_a_bad_model_table_is_refused(tmp_path: Path, clean_env) -> None:
    card_path = _card_only(tmp_path)
    text = card_path.read_text()
    cases = [
        (text.replace("frame_skip = 2", "frame_skip = 0"), "frame_skip"),
        (text.replace('mjcf = "../cartpole.xml"', 'mjcf = "../cartpole.txt"'), "expected an MJCF file"),
        (text.replace("max_episode_steps = 1000", "max_episode_steps = 1.5"), "max_episode_steps"),
        (text.replace("[model]", "[model]\nxml = 1"), "unknown field(s) ['xml']"),
    ]
    for bad, message in cases:
        card_path.write_text(bad)
        with pytest.raises(ModelCardError, match=None) as caught:
            load_card(card_path)
        assert message in str(caught.value), str(caught.value)
    card_path.write_text(text.replace('mjcf = "../cartpole.xml"', 'mjcf = "../gone.xml"'))
    from pidlab.plant.card_env import CardEnv

    with pytest.raises(ModelCardError, match="does not exist"):
        CardEnv(card=card_path)


def test_the_control_journeys_run_on_a_bare_mjcf_and_training_names_the_scaffold(tmp_path: Path) -> None:
    _card_only(tmp_path, "BareCartPole-v0")
    env = {k: v for k, v in os.environ.items() if k not in VARIABLES}
    env["PIDLAB_MODELS"] = str(tmp_path / "models")
    spec = "tuning/BareCartPole-v0.pidlab-robust.toml"
    steps = [
        ["tune", "cartpole.xml", "--auto"],
        ["analyze", spec, "--episodes", "1"],
        ["bounds", spec, "--samples", "40", "--write"],
        ["rescue", spec, "--validation", "200", "--coverage", "200", "--write"],
    ]
    for args in steps:
        done = subprocess.run(
            [PIDLAB, *args], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600
        )
        assert done.returncode == 0 and "Traceback" not in done.stderr, (args, done.stderr[-2000:])
        if args[0] == "analyze":  # the coach alone ran a full episode on the card's env
            assert "1x time limit" in done.stdout, done.stdout[-2000:]
    # the tuner serves the file's card and its coach (its preview's episodes run on a CardEnv)
    with_models = {**os.environ, "PIDLAB_MODELS": env["PIDLAB_MODELS"]}
    serve_ui([PIDLAB, "tune", "cartpole.xml", "--ui", "--spec", spec], tmp_path, with_models)
    preview = subprocess.run(
        [sys.executable, "-c", PREVIEW], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600
    )
    assert preview.returncode == 0 and preview.stdout.split() == ["2", "1000.0", "False"], preview.stderr[-2000:]
    for args in (["train", "cartpole.xml"], ["train", "BareCartPole-v0"], ["run", "cartpole.xml"]):
        done = subprocess.run(
            [PIDLAB, *args], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300
        )
        assert done.returncode == 2 and "pidlab init" in done.stderr, (args, done.stderr)
        assert len(done.stderr.strip().splitlines()) == 1


def test_a_project_module_that_cannot_be_imported_is_named_only_when_needed(tmp_path: Path, clean_env) -> None:
    (tmp_path / "pidlab.toml").write_text('schema = "pidlab.project/1"\ngym_packages = ["no_such_robots_here"]\n')
    clean_env.chdir(tmp_path)
    code, err = cli_in_process("linearize", "InvertedPendulum-v5")  # registered: the module is not needed
    assert code == 0, err
    code, err = cli_in_process("linearize", "MyRobot-v0")
    assert code == 2 and "cannot import 'no_such_robots_here'" in err and "pidlab.toml" in err
    assert len(err.strip().splitlines()) == 1


def test_a_project_file_named_like_an_installed_package_does_not_hide_it(tmp_path: Path) -> None:
    """The folder goes at the end of the search path: ``control.py`` there is not python-control,
    in the command's process or in the processes it starts, while the project's own modules load."""
    (tmp_path / "control.py").write_text("raise SystemExit('the project shadowed python-control')\n")
    (tmp_path / "robots_here.py").write_text("import control\nFOUND = control.__file__\n")
    (tmp_path / "pidlab.toml").write_text('schema = "pidlab.project/1"\ngym_packages = ["robots_here"]\n')
    env = {k: v for k, v in os.environ.items() if k not in VARIABLES}
    probe = (
        "import multiprocessing as mp\n"
        "from pidlab.plant.envs import import_module\n"
        "def child(q):\n"
        "    import_module('robots_here', 'test'); import robots_here; q.put(robots_here.FOUND)\n"
        "if __name__ == '__main__':\n"
        "    from pidlab.project import apply_project, load_project\n"
        "    apply_project(load_project('pidlab.toml'))\n"
        "    import control; print(control.__file__)\n"
        "    ctx = mp.get_context('spawn'); q = ctx.Queue(); p = ctx.Process(target=child, args=(q,))\n"
        "    p.start(); print(q.get(timeout=120)); p.join()\n"
    )
    (tmp_path / "probe.py").write_text(probe)
    done = subprocess.run([sys.executable, "probe.py"], cwd=tmp_path, env={**env, "PYTHONSAFEPATH": "1"},
                          capture_output=True, text=True, timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    here, child = done.stdout.split()
    assert str(tmp_path) not in here and str(tmp_path) not in child  # python-control, both times
