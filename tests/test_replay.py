"""The coach's transitions in a buffer of their own (``coach_buffer``, SAC): what enters each buffer,
how batches mix them, how many gradient steps each env step buys, checkpoints, and bad input.

Mechanics, not luck: budgets of a few hundred env steps on a small network; nothing here asserts
that an agent learned.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import tomli_w

from pidlab.controller.spec import load_spec
from pidlab.errors import CoachingError, RecipeError
from pidlab.files import read_json
from pidlab.rl.coaching import CoachingWrapper
from pidlab.rl.couplings import check_couplings
from pidlab.rl.recipe import CoachBuffer, load_recipe, parse_coaching, parse_recipe, recipe_to_dict
from pidlab.rl.replay import MixedBatches, coach_rows, updates_per_env_step
from pidlab.rl.rundir import latest_checkpoint
from pidlab.rl.train import resume, train
from tests.helpers import COACH, SHIELD, TUNING, cli_in_process, sac_recipe_data

IP = "InvertedPendulum-v5"
def recipe_data(**coaching) -> dict:
    """The small SAC recipe of the helpers, with a coach buffer unless ``coaching`` says otherwise."""
    return sac_recipe_data(**{"coach_buffer": {"share": 0.5}, **coaching})


def tiny(**coaching):
    return parse_recipe(recipe_data(**coaching), "tiny")


@pytest.fixture(scope="module")
def spec():
    return load_spec(TUNING / f"{IP}.pidlab-rescue.toml")


# ----------------------------------------------------------------------------- the recipe field


def test_the_field_reads_writes_and_defaults():
    assert parse_coaching({"coach_buffer": {}}).coach_buffer == CoachBuffer(share=0.5, size=None)
    recipe = tiny(coach_buffer={"share": 0.25, "size": 300})
    assert recipe.coaching.coach_buffer == CoachBuffer(0.25, 300)
    assert parse_recipe(recipe_to_dict(recipe), "again").coaching.coach_buffer == CoachBuffer(0.25, 300)
    assert "coach_buffer" not in recipe_to_dict(load_recipe(COACH / f"{IP}.toml"))["coaching"]


@pytest.mark.parametrize(
    ("field", "message"),
    [
        ({"share": 1.5}, "coaching.coach_buffer.share"),
        ({"share": -0.1}, "coaching.coach_buffer.share"),
        ({"share": "half"}, "coaching.coach_buffer.share"),
        ({"size": 0}, "coaching.coach_buffer.size"),
        ({"ratio": 1}, "unknown field(s) ['ratio']"),
        (0.5, "coaching.coach_buffer"),
    ],
)
def test_a_bad_field_is_refused_naming_it(field, message):
    with pytest.raises(RecipeError, match=None) as info:
        parse_coaching({"coach_buffer": field})
    assert message in str(info.value)


def test_it_needs_sac_a_coach_a_view_that_labels_and_steps(spec):
    check_couplings(tiny(), spec)  # the shipped shape is fine
    cases = [
        (tiny(), None, "this run has no coach"),
        (dataclasses.replace(tiny(), algo="ppo"), spec, "use algo = 'sac'"),
        (tiny(view="hidden"), spec, "use view = 'terminal' or 'penalty'"),
    ]
    episodic = recipe_data()
    episodic["sac"]["train_freq"] = [1, "episode"]
    cases.append((parse_recipe(episodic, "tiny"), spec, "train_freq = n (steps)"))
    for recipe, coach, message in cases:
        with pytest.raises(CoachingError) as info:
            check_couplings(recipe, coach)
        assert message in str(info.value)


def test_the_command_line_refuses_them_in_one_line(tmp_path):
    for name, data, message in [
        ("share.toml", recipe_data(coach_buffer={"share": 2}), "coaching.coach_buffer.share"),
        ("ppo.toml", {**recipe_data(), "algo": "ppo"}, "use algo = 'sac'"),
    ]:
        path = tmp_path / name
        path.write_text(tomli_w.dumps(data))
        code, stderr = cli_in_process("train", IP, "--coach", "pidlab-rescue", "--recipe", str(path),
                                      "--run-dir", str(tmp_path / "r"))  # fmt: skip
        lines = stderr.strip().splitlines()
        assert code == 2 and len(lines) == 1 and message in lines[0], stderr
        assert not (tmp_path / "r").exists()


def test_a_condition_with_a_coach_buffer_and_ppo_is_refused_before_any_run(tmp_path):
    conditions = tmp_path / "c.toml"
    conditions.write_text(tomli_w.dumps({"schema": "pidlab.conditions/1", "condition": {"pvp": {
        "description": "d", "coach": "pidlab-rescue", "coaching": {**SHIELD, "coach_buffer": {"share": 0.5}}}}}))
    code, stderr = cli_in_process("experiment", "--envs", IP, "--conditions", "pvp", "--conditions-file",
                                  str(conditions), "--seeds", "1", "--algo", "ppo", "--out", str(tmp_path / "x"))  # fmt: skip
    assert code == 2 and "use algo = 'sac'" in stderr and len(stderr.strip().splitlines()) == 1, stderr
    assert not (tmp_path / "x").exists()


# ----------------------------------------------------------------------------- the wrapper's record


def test_the_wrapper_reports_each_coach_step_of_a_rescue(spec):
    env = CoachingWrapper(gym.make(IP), spec, **SHIELD, record=True)
    silent = CoachingWrapper(gym.make(IP), spec, **SHIELD)
    obs, _ = env.reset(seed=4)
    silent.reset(seed=4)
    reported = 0
    for _ in range(300):
        before = obs
        obs, _, terminated, truncated, info = env.step(np.array([3.0], dtype=np.float32))
        same = silent.step(np.array([3.0], dtype=np.float32))
        np.testing.assert_array_equal(same[0], obs)  # recording changes nothing
        assert "coach_transitions" not in same[4]
        rows = info.get("coach_transitions")
        if info["coach_steps"] == 0:
            assert rows is None
        else:
            reported += 1
            n = len(rows["rewards"])
            assert n == info["coach_steps"]
            np.testing.assert_array_equal(rows["obs"][0], before)  # a veto: the coach acts from s
            np.testing.assert_array_equal(rows["obs"][1:], rows["next_obs"][:-1])  # a chain of steps
            assert rows["rewards"].sum() == pytest.approx(info["coach_reward"])
            assert not rows["terminated"][:-1].any() and not rows["truncated"][:-1].any()
            assert np.all(np.abs(rows["actions"]) <= 3.0)
        if terminated or truncated:
            obs, _ = env.reset()
            silent.reset()
    assert reported > 5


def test_roll_in_steps_are_not_reported(spec):
    env = CoachingWrapper(gym.make(IP), spec, **SHIELD, record=True)
    env.set_rollin(20)
    env.reset(seed=1)
    _, _, _, _, info = env.step(np.zeros(1, dtype=np.float32))
    assert info["rollin"]["steps"] == 20
    assert len(info.get("coach_transitions", {"rewards": []})["rewards"]) == info["coach_steps"]


# ----------------------------------------------------------------------------- batches


@pytest.mark.parametrize(
    ("share", "batch", "agent", "coach", "rows"),
    [(0.5, 256, 10, 10, 128), (0.5, 5, 10, 10, 3), (0.0, 64, 10, 10, 0), (1.0, 64, 10, 10, 64),
     (0.5, 64, 0, 10, 64), (0.5, 64, 10, 0, 0), (0.25, 10, 1, 1, 3), (0.3, 10, 5, 5, 3)],
)  # fmt: skip
def test_coach_rows_hand_computed(share, batch, agent, coach, rows):
    assert coach_rows(share, batch, agent, coach) == rows


def test_updates_per_env_step_hand_computed():
    assert updates_per_env_step(-1, 1, 1) == 1.0
    assert updates_per_env_step(8, 8, 1) == 1.0
    assert updates_per_env_step(1, 1, 4) == 0.25
    assert updates_per_env_step(2, 1, 1) == 2.0


def test_a_mixed_batch_holds_agent_rows_then_coach_rows():
    from stable_baselines3.common.buffers import ReplayBuffer

    space = gym.spaces.Box(-1, 1, (2,))
    agent, coach = (ReplayBuffer(50, space, space, device="cpu") for _ in range(2))
    for _ in range(20):
        agent.add(np.full((1, 2), 1.0), np.zeros((1, 2)), np.zeros((1, 2)), np.array([1.0]), np.array([0.0]), [{}])
        coach.add(np.full((1, 2), -1.0), np.zeros((1, 2)), np.zeros((1, 2)), np.array([-1.0]), np.array([0.0]), [{}])
    mixed = MixedBatches(agent, coach, 0.25)
    batch = mixed.sample(8)
    assert batch.rewards.flatten().tolist() == [1.0] * 6 + [-1.0] * 2
    assert batch.observations.shape == (8, 2) and mixed.coach_rows_drawn == 2


# ----------------------------------------------------------------------------- training


@pytest.fixture(scope="module")
def run(tmp_path_factory, spec):
    folder = tmp_path_factory.mktemp("pvp") / "run"
    result = train(tiny(), spec, folder, progress_bar=False)
    return folder, result


def test_each_buffer_holds_what_the_docs_say(run):
    folder, result = run
    state = read_json(latest_checkpoint(folder) / "state.json")
    from pidlab.rl.checkpoint import _read_npz

    agent = _read_npz(latest_checkpoint(folder) / "replay_buffer.npz")
    coach = _read_npz(latest_checkpoint(folder) / "coach_buffer.npz")
    assert result.completed and result.coach_steps > 0
    # the coach's buffer: one transition per coach step; the agent's: one per agent action, the
    # vetoed ones included (each labelled a failure: the agent's episode ended there)
    assert len(coach["rewards"]) == result.coach_steps == state["sb3"]["coach_transitions"]
    vetoes = result.interventions
    assert len(agent["rewards"]) == result.agent_steps + vetoes
    assert int(agent["dones"].sum()) >= vetoes
    assert np.all(np.abs(coach["actions"]) <= 1.0)  # scaled as SB3 scales the agent's
    # SB3's step count is the run's env steps (the coach's added, vetoed actions not counted)
    assert state["num_timesteps"] == result.env_steps == state["env_steps"]


def test_every_env_step_after_learning_starts_buys_one_gradient_step(run):
    folder, result = run
    state = read_json(latest_checkpoint(folder) / "state.json")
    sb3 = state["sb3"]
    # rate 1 (gradient_steps = train_freq = 8): every coach step counted before the last update
    # bought one; those of the last rollout are unspent when the budget ends it, as SB3's are
    assert 0 < sb3["coach_updates"] <= sb3["coach_counted"]
    assert state["policy_updates"] == sb3["n_updates"]
    agent_updates = sb3["n_updates"] - sb3["coach_updates"]
    assert agent_updates % 8 == 0  # SB3's own: 8 per rollout of 8 agent steps
    after = result.env_steps - 100  # env steps after learning_starts
    unspent = sb3["coach_counted"] - sb3["coach_updates"]
    assert after - 8 <= sb3["n_updates"] + unspent <= after + 8  # SB3 trains once per rollout of 8


def test_coach_steps_buy_gradient_steps_at_the_recipes_rate(spec):
    from pidlab.rl.replay import CoachReplaySAC
    from pidlab.rl.train import make_vec_env, sb3_arguments

    recipe = tiny()
    venv = make_vec_env(recipe, spec)
    model = CoachReplaySAC(policy="MlpPolicy", env=venv, seed=0, device="cpu", **sb3_arguments(recipe))
    model.learn(120)  # past learning_starts (100): SB3 trains after each rollout of 8 agent steps
    n, counted, updates = model._n_updates, model.coach_counted, model.coach_updates
    obs = np.zeros((1, 4))
    rows = {"obs": np.zeros((5, 4)), "actions": np.zeros((5, 1)), "rewards": np.ones(5),
            "next_obs": np.zeros((5, 4)), "terminated": np.zeros(5, bool), "truncated": np.zeros(5, bool)}  # fmt: skip
    model._last_obs, model._last_original_obs = obs, obs
    steps = model.num_timesteps
    model._store_transition(model.replay_buffer, np.zeros((1, 1)), obs, np.ones(1), np.zeros(1, bool),
                            [{"coach_transitions": rows, "vetoed": True}])  # fmt: skip
    assert model.num_timesteps == steps + 5 - 1  # the vetoed action never ran
    assert model.coach_counted == counted + 5 - 1 and model.coach_transitions >= 5
    model.train(gradient_steps=8, batch_size=16)
    # 8 for the agent's actions, one per coach step, less one for the vetoed action
    assert model._n_updates == n + 8 + (counted + 4 - updates)
    assert model.coach_updates == model.coach_counted
    venv.close()


def test_same_seed_same_buffers(run, spec, tmp_path):
    folder, _ = run
    again = tmp_path / "again"
    train(tiny(), spec, again, progress_bar=False)
    from pidlab.rl.checkpoint import _read_npz

    for name in ("coach_buffer.npz", "replay_buffer.npz"):
        a, b = _read_npz(latest_checkpoint(folder) / name), _read_npz(latest_checkpoint(again) / name)
        assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


def test_a_resume_keeps_the_coach_buffer_and_its_counters(run, tmp_path):
    import shutil

    folder, _ = run
    copy = tmp_path / "copy"
    shutil.copytree(folder, copy)
    before = read_json(latest_checkpoint(copy) / "state.json")["sb3"]
    extended = resume(copy, steps=600, progress_bar=False)
    after = read_json(latest_checkpoint(copy) / "state.json")
    assert extended.completed and after["num_timesteps"] == extended.env_steps >= 600
    assert after["sb3"]["coach_transitions"] == extended.coach_steps > before["coach_transitions"]
    assert before["coach_updates"] < after["sb3"]["coach_updates"] <= after["sb3"]["coach_counted"]
    from pidlab.rl.checkpoint import _read_npz

    assert len(_read_npz(latest_checkpoint(copy) / "coach_buffer.npz")["rewards"]) == extended.coach_steps


def test_a_checkpoint_without_its_coach_buffer_is_damaged(run, tmp_path):
    import shutil

    from pidlab.errors import CheckpointError
    from pidlab.rl.train import load_checkpoint, make_vec_env

    folder, _ = run
    copy = tmp_path / "copy"
    shutil.copytree(folder, copy)
    checkpoint = latest_checkpoint(copy)
    (checkpoint / "coach_buffer.npz").write_bytes(b"not a buffer")
    recipe = tiny()
    venv = make_vec_env(recipe, load_spec(TUNING / f"{IP}.pidlab-rescue.toml"))
    with pytest.raises(CheckpointError, match="coach_buffer.npz: damaged"):
        load_checkpoint(checkpoint, recipe, venv)
    venv.close()


def test_the_final_agent_loads_without_its_buffers(run):
    folder, _ = run
    summary = read_json(folder / "summary.json")
    assert sorted(summary["files"]) == ["model.zip"]  # the shipped [sac] tables normalize nothing
    assert Path(folder / "final_model.zip").is_file()


def test_the_model_archive_does_not_hold_the_coach_buffer_again(run):
    """SB3's ``save`` pickled every attribute it does not exclude into the archive's ``data``: the
    coach's buffer, at its capacity, went in beside ``coach_buffer.npz`` (64 MB of a 69.5 MB
    InvertedDoublePendulum checkpoint). The agent's buffer never did; now neither does the coach's."""
    import json
    import zipfile

    folder, _ = run
    for archive in (latest_checkpoint(folder) / "model.zip", folder / "final_model.zip"):
        with zipfile.ZipFile(archive) as z:
            data = json.loads(z.read("data"))
        assert "coach_buffer" not in data and "replay_buffer" not in data
        assert data["coach_transitions"] > 0  # the counters stay: a loaded agent knows what it saw


# ----------------------------------------------------------------------------- demonstrations, for SAC


@pytest.mark.parametrize("normalize", [False, True])
def test_sac_keeps_the_coachs_demonstrations_in_the_coach_buffer(spec, tmp_path, normalize):
    """Demonstrations as long as learning_starts take the random warm-up's place, in the coach's buffer."""
    from pidlab.rl import demonstrations as demo
    from pidlab.rl.checkpoint import _read_npz

    # noise as wide as the action range, so that the coach falls and ended steps are checked too
    data = recipe_data(off_after=0.0, view="hidden", demonstrations={"steps": 100, "noise": 1.0})
    if normalize:  # raw observations in both buffers, as SB3 stores its own behind a VecNormalize
        data["sac"]["normalize"] = {"obs": True, "reward": False}
    folder = tmp_path / "run"
    result = train(parse_recipe(data, "tiny"), spec, folder, progress_bar=False)
    demos = demo.load(folder / demo.FILE)
    coach = _read_npz(latest_checkpoint(folder) / "coach_buffer.npz")
    state = read_json(latest_checkpoint(folder) / "state.json")
    assert read_json(folder / "warm_start.json")["coach_buffer_rows"] == len(demos) == 100
    # the coach never acts after its demonstrations: they are the coach buffer, row for row
    assert state["sb3"]["coach_transitions"] == len(coach["rewards"]) == 100 == result.coach_steps
    assert np.array_equal(coach["observations"][:, 0], demos.obs)
    assert np.array_equal(coach["next_observations"][:, 0], demos.next_obs)
    assert np.allclose(coach["actions"][:, 0], demos.actions / 3.0, atol=1e-6)  # scaled as SB3 does: +-3
    assert np.array_equal(coach["rewards"][:, 0], demos.rewards.astype(np.float32))
    ended = demos.terminated | demos.truncated
    assert np.array_equal(coach["dones"][:, 0].astype(bool), ended)
    # a step's next observation is the next step's observation, unless the step ended an episode
    going = ~ended[:-1]
    assert np.array_equal(demos.next_obs[:-1][going], demos.obs[1:][going])
    assert demos.terminated.any()
    for i in np.flatnonzero(ended[:-1]):  # the last observation of the episode, not the next reset
        assert abs(demos.next_obs[i][1]) > 0.2 and not np.array_equal(demos.next_obs[i], demos.obs[i + 1])
    # they were env steps: SB3 counted them, and no random warm-up step followed
    assert state["num_timesteps"] == result.env_steps == 400
    agent = _read_npz(latest_checkpoint(folder) / "replay_buffer.npz")
    assert len(agent["rewards"]) == result.agent_steps == 300
    # learning started right after them: every agent env step bought one gradient step
    assert 300 - 8 <= state["sb3"]["n_updates"] <= 300


def test_sac_learning_starts_right_after_demonstrations_shorter_than_its_warm_up(spec, tmp_path):
    """The demonstrations are SAC's warm-up: 50 of them end a warm-up of 100 (learning_starts) at 50."""
    from pidlab.rl.checkpoint import _read_npz

    data = recipe_data(off_after=0.0, view="hidden", demonstrations={"steps": 50, "noise": 0.1})
    assert data["sac"]["learning_starts"] == 100
    result = train(parse_recipe(data, "tiny"), spec, tmp_path / "run", progress_bar=False)
    state = read_json(latest_checkpoint(tmp_path / "run") / "state.json")
    agent = _read_npz(latest_checkpoint(tmp_path / "run") / "replay_buffer.npz")
    assert result.coach_steps == 50 and len(agent["rewards"]) == result.agent_steps == 350
    # every agent env step bought one gradient step (SB3 trains once per rollout of 8), none random
    assert 350 - 8 <= state["sb3"]["n_updates"] <= 350


def test_sac_demonstrations_behind_the_shield_share_the_coach_buffer_with_its_rescues(spec, tmp_path):
    """demo-replay-shield: the demonstrations first, then the coach's steps of every veto, in one buffer."""
    from pidlab.rl import demonstrations as demo
    from pidlab.rl.checkpoint import _read_npz

    data = recipe_data(demonstrations={"steps": 100, "noise": 0.1})  # the helpers' rescue-terminal shield
    folder = tmp_path / "run"
    result = train(parse_recipe(data, "tiny"), spec, folder, progress_bar=False)
    demos = demo.load(folder / demo.FILE)
    coach = _read_npz(latest_checkpoint(folder) / "coach_buffer.npz")
    agent = _read_npz(latest_checkpoint(folder) / "replay_buffer.npz")
    state = read_json(latest_checkpoint(folder) / "state.json")
    rescues = result.coach_steps - len(demos)
    assert len(demos) == 100 and rescues > 0 and result.interventions > 0  # the shield acted after them
    assert state["sb3"]["coach_transitions"] == len(coach["rewards"]) == result.coach_steps
    assert np.array_equal(coach["observations"][:100, 0], demos.obs)  # the demonstrations lead the buffer
    # the agent's buffer: its actions only, the vetoed ones included; none of the demonstrations
    assert len(agent["rewards"]) == result.agent_steps + result.interventions
    # every rescue step bought a gradient step, less one per vetoed action (SB3 bought that one)
    assert state["sb3"]["coach_counted"] == rescues - result.interventions
    # a rescue under way at the budget finishes first, so the run may end a few env steps over it
    assert state["num_timesteps"] == result.env_steps >= 400


def test_sac_demonstrations_without_a_coach_buffer_are_refused(spec):
    recipe = parse_recipe(sac_recipe_data(off_after=0.0, demonstrations={"steps": 100, "noise": 0.1}), "tiny")
    with pytest.raises(CoachingError, match="add coaching.coach_buffer"):
        check_couplings(recipe, spec)
    # a coach buffer with the hidden view is refused only while the coach may take over
    check_couplings(tiny(off_after=0.0, view="hidden", demonstrations={"steps": 100, "noise": 0.1}), spec)
    with pytest.raises(CoachingError, match="use view = 'terminal' or 'penalty'"):
        check_couplings(tiny(view="hidden", demonstrations={"steps": 100, "noise": 0.1}), spec)


def test_demonstrations_written_before_next_observations_load_without_them(tmp_path):
    from pidlab.rl import demonstrations as demo

    arrays = {"obs": np.zeros((3, 4), np.float32), "actions": np.zeros((3, 1), np.float32),
              "rewards": np.ones(3), "terminated": np.zeros(3, bool), "truncated": np.zeros(3, bool),
              "env_index": np.zeros(3, np.int64)}  # fmt: skip
    np.savez(tmp_path / "old.npz", **arrays)
    old = demo.load(tmp_path / "old.npz")
    assert old.next_obs is None and len(old) == 3
    np.savez(tmp_path / "bad.npz", **arrays, next_obs=np.zeros((2, 4), np.float32))
    with pytest.raises(CoachingError, match="disagree in length or shape"):
        demo.load(tmp_path / "bad.npz")
