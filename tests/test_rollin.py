"""Roll-ins (Jump-Start RL): what the coach runs first, what is charged, how the stage moves, resume."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import gymnasium as gym
import numpy as np
import pytest
import tomli_w
import tomllib

from pidlab.controller.pid import Coach
from pidlab.controller.spec import load_spec
from pidlab.errors import CoachingError, RecipeError
from pidlab.plant.model import load_model
from pidlab.rl.coaching import CoachingWrapper
from pidlab.rl.couplings import ROLLIN_RECORD, RollInCoupling
from pidlab.rl.recipe import RollIn, load_recipe, parse_recipe, recipe_to_dict
from pidlab.rl.rundir import read_csv_rows
from pidlab.rl.train import Counters, resume, train
from tests.helpers import ROOT, TUNING, cli_in_process

IP = "InvertedPendulum-v5"


@pytest.fixture(scope="module")
def spec():
    return load_spec(TUNING / f"{IP}.pidlab-rescue.toml")


def _data(steps: int, rollin: dict, every: int = 1000) -> dict:
    data = tomllib.loads((ROOT / "coach" / f"{IP}.toml").read_text())
    data["steps"] = steps
    data["evaluation"] = {"every": every, "episodes": 2, "seed": 1000000}
    data["checkpoint"] = {"every": 1000}
    data["ppo"].pop("n_envs")  # one env: each reset's roll-in is charged in order
    data["ppo"]["n_steps"] = 64
    data["coaching"] = {**data["coaching"], "off_after": 0.0, "rollin": rollin}
    return data


# ------------------------------------------------------------------------------- the recipe field


@pytest.mark.parametrize(
    ("rollin", "message"),
    [
        ({"stages": 1}, "rollin.stages"),
        ({"stages": 2.5}, "rollin.stages"),
        ({"tolerance": 1.5}, "rollin.tolerance"),
        ({"tolerance": -0.1}, "rollin.tolerance"),
        ({"horizon": 10}, "unknown field"),
        (True, "coaching.rollin"),
    ],
)
def test_bad_rollin_fields_are_refused_by_name(rollin, message: str) -> None:
    with pytest.raises(RecipeError, match="coaching.rollin") as err:
        parse_recipe(_data(1000, rollin))
    assert message in str(err.value)


def test_the_rollin_field_round_trips_with_its_defaults() -> None:
    r = parse_recipe(_data(1000, {}))
    assert r.coaching.rollin == RollIn(stages=10, tolerance=0.1)
    assert parse_recipe(recipe_to_dict(r)) == r


def test_a_rollin_without_a_coach_is_one_line_and_exit_2(tmp_path: Path) -> None:
    path = tmp_path / "r.toml"
    path.write_text(tomli_w.dumps(_data(1000, {})))
    with pytest.raises(CoachingError, match="no coach"):
        train(load_recipe(path), None, tmp_path / "a", progress_bar=False)
    assert not (tmp_path / "a").exists()
    code, out = cli_in_process("train", IP, "--coach", "none", "--recipe", str(path), "--run-dir",
                               str(tmp_path / "b"), "--no-progress")  # fmt: skip
    assert code == 2 and len(out.strip().splitlines()) == 1 and "roll-in" in out


# ------------------------------------------------------------------------------- the schedule


def test_the_stages_and_thresholds_by_hand() -> None:
    c = RollInCoupling(RollIn(stages=10, tolerance=0.1), horizon=1000)
    assert [c.steps_at(k) for k in (0, 1, 8, 9, 12)] == [900, 800, 100, 0, 0]
    assert c.threshold(0) == pytest.approx(90.0) and c.threshold(8) == pytest.approx(810.0)
    odd = RollInCoupling(RollIn(stages=3, tolerance=0.0), horizon=1000)
    assert [odd.steps_at(k) for k in range(3)] == [667, 334, 0]  # rounded up


def _fake_trainer(tmp_path: Path, env_steps: int, stage: int) -> SimpleNamespace:
    calls: list[tuple] = []
    venv = SimpleNamespace(env_method=lambda *a: calls.append(a))
    tb = SimpleNamespace(add_scalar=lambda *a: None)
    return SimpleNamespace(counters=Counters(env_steps=env_steps, rollin_stage=stage), venv=venv, tb=tb,
                           run_dir=tmp_path, calls=calls)  # fmt: skip


def test_the_stage_moves_one_step_when_the_agent_alone_lasts_its_share(tmp_path: Path) -> None:
    c = RollInCoupling(RollIn(stages=10, tolerance=0.1), horizon=1000)
    t = _fake_trainer(tmp_path, env_steps=0, stage=0)
    c.on_session(t)
    assert t.calls == [("set_rollin", 900)]
    c.after_evaluation(t, SimpleNamespace(mean_length=1000.0))  # env step 0: never moves
    t.counters.env_steps = 2500
    c.after_evaluation(t, SimpleNamespace(mean_length=89.9))  # below 0.9 * 100
    assert t.counters.rollin_stage == 0 and len(t.calls) == 1
    c.after_evaluation(t, SimpleNamespace(mean_length=1000.0))  # one stage per evaluation
    assert t.counters.rollin_stage == 1 and t.calls[-1] == ("set_rollin", 800)
    t.counters.rollin_stage = 9
    c.after_evaluation(t, SimpleNamespace(mean_length=1000.0))  # the last stage stays
    assert t.counters.rollin_stage == 9
    changes = json.loads((tmp_path / ROLLIN_RECORD).read_text())["changes"]
    assert changes == [
        {"env_steps": 0, "stage": 0, "steps": 900},
        {"env_steps": 2500, "stage": 1, "steps": 800},
    ]
    # a resume from env step 1000 forgets the change recorded after it
    t2 = _fake_trainer(tmp_path, env_steps=1000, stage=0)
    c.on_session(t2)
    assert json.loads((tmp_path / ROLLIN_RECORD).read_text())["changes"] == changes[:1]


# ------------------------------------------------------------------------------- the wrapper


def test_the_coach_rolls_in_for_h_steps_and_the_next_step_reports_them(spec) -> None:
    env = CoachingWrapper(gym.make(IP), spec, off_after=0.0)
    env.set_rollin(30)
    obs, info = env.reset(seed=3)
    # a twin replays the coach from the same reset: the agent's first observation is after 30 coach steps
    twin_env, twin = gym.make(IP), Coach(spec, load_model(IP))
    o, _ = twin_env.reset(seed=3)
    twin.reset(o)
    for _ in range(30):
        o, *_ = twin_env.step(twin.act(o))
    np.testing.assert_array_equal(obs, o)
    assert info["rollin_steps"] == 30 and env.unwrapped.data.time == pytest.approx(30 * env.unwrapped.dt)
    _, _, _, _, info = env.step(np.zeros(1, dtype=np.float32))
    assert info["rollin"] == {"steps": 30, "episodes": []} and info["episode_coach_steps"] == 30
    assert info["coach_steps"] == 0 and info["episode_agent_steps"] == 1
    _, _, _, _, info = env.step(np.zeros(1, dtype=np.float32))
    assert "rollin" not in info  # reported once


def test_a_rollin_that_ends_the_episode_is_logged_and_the_env_reset_without_one(spec) -> None:
    env = CoachingWrapper(gym.make(IP, max_episode_steps=20), spec, off_after=0.0)
    env.set_rollin(25)  # longer than the time limit: the roll-in is cut at 20 steps
    env.reset(seed=0)
    assert env.unwrapped.data.time == 0.0  # reset again, no roll-in this time
    assert env.total_env_resets == 2 and env.total_coach_steps == 20
    _, _, _, _, info = env.step(np.zeros(1, dtype=np.float32))
    (record,) = info["rollin"]["episodes"]
    assert info["rollin"]["steps"] == 20
    assert record["agent_steps"] == 0 and record["coach_steps"] == 20 and record["env_end"]
    assert not record["fell"] and record["runs"] == 0
    assert info["episode_coach_steps"] == 0 and info["episode_agent_steps"] == 1


def test_set_rollin_refuses_bad_values(spec) -> None:
    env = CoachingWrapper(gym.make(IP), spec)
    for bad in (-1, 2.5, True, "3"):
        with pytest.raises(CoachingError, match="roll-in steps"):
            env.set_rollin(bad)
    with pytest.raises(CoachingError, match="needs a coach"):
        CoachingWrapper(gym.make(IP), None).set_rollin(5)
    CoachingWrapper(gym.make(IP), None).set_rollin(0)


# ------------------------------------------------------------------------------- training


@pytest.fixture(scope="module")
def rollin_run(tmp_path_factory: pytest.TempPathFactory, spec) -> Path:
    folder = tmp_path_factory.mktemp("rollin")
    path = folder / "r.toml"
    # two stages: 500 coach steps, then none once the agent alone lasts 500 steps (not in 3,000 steps)
    path.write_text(tomli_w.dumps(_data(3000, {"stages": 2, "tolerance": 0.0})))
    train(load_recipe(path), spec, folder / "run", progress_bar=False)
    return folder / "run"


def test_every_rollin_step_is_charged_and_each_episode_starts_with_one(rollin_run: Path) -> None:
    s = json.loads((rollin_run / "summary.json").read_text())
    eps = read_csv_rows(rollin_run / "episodes.csv")
    assert s["completed"] and s["rollin_stage"] == 0 and s["interventions"] == 0
    assert s["env_steps"] == s["agent_steps"] + s["coach_steps"] >= 3000
    # one env, no takeover: every coach step is a roll-in of 500, one per real reset
    assert s["coach_steps"] == 500 * s["env_resets"]
    assert all(int(e["coach_steps"]) == 500 for e in eps)
    assert s["falls"] == sum(int(e["fell"]) for e in eps) and s["env_episodes"] == len(eps)
    assert all(int(e["runs"]) == 1 and int(e["longest_run"]) == int(e["agent_steps"]) for e in eps)
    # the log's running totals count each roll-in before the episode's agent steps
    for e in eps:
        assert int(e["env_steps_so_far"]) >= int(e["agent_steps_so_far"]) + 500


def test_a_resumed_rollin_run_rolls_in_again_and_matches_the_uninterrupted_one(
    rollin_run: Path, tmp_path: Path, spec
) -> None:
    path = tmp_path / "r.toml"
    path.write_text(tomli_w.dumps(_data(3000, {"stages": 2, "tolerance": 0.0})))
    short = tmp_path / "short"
    train(load_recipe(path), spec, short, progress_bar=False)  # the same run
    assert read_csv_rows(short / "episodes.csv") == read_csv_rows(rollin_run / "episodes.csv")  # same seed
    done = resume(short, steps=4500, progress_bar=False)
    s = json.loads((short / "summary.json").read_text())
    eps = read_csv_rows(short / "episodes.csv")
    assert done.completed and s["coach_steps"] == 500 * s["env_resets"]
    assert all(int(e["coach_steps"]) == 500 for e in eps)
    record = json.loads((short / ROLLIN_RECORD).read_text())
    assert record["horizon"] == 1000 and record["changes"][0] == {"env_steps": 0, "stage": 0, "steps": 500}
