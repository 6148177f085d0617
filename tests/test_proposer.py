"""The coach as a proposer (``proposer``, SAC, IBRL-style): the pick, what the buffer holds, the
target that weighs the proposals, checkpoints, and bad input.

Mechanics, not luck: nothing here asserts that an agent learned.
"""

from __future__ import annotations

import shutil

import gymnasium as gym
import numpy as np
import pytest
import tomli_w
import torch

from pidlab.controller.pid import Coach
from pidlab.controller.spec import load_spec
from pidlab.errors import CoachingError, RecipeError
from pidlab.files import read_json
from pidlab.plant.model import load_model
from pidlab.rl.checkpoint import _read_npz
from pidlab.rl.coaching import CoachingWrapper
from pidlab.rl.couplings import check_couplings
from pidlab.rl.proposer import ProposalTarget, _Stash
from pidlab.rl.recipe import Proposer, parse_coaching, parse_recipe, recipe_to_dict
from pidlab.rl.rundir import latest_checkpoint
from pidlab.rl.train import load_checkpoint, make_vec_env, resume, train
from tests.helpers import SHIELD, TUNING, changed_recipe, cli_in_process, sac_recipe_data

IP = "InvertedPendulum-v5"


@pytest.fixture(scope="module")
def spec():
    return load_spec(TUNING / f"{IP}.pidlab-rescue.toml")


def data(**coaching) -> dict:
    return sac_recipe_data(proposer={"until": 0.8}, **coaching)


def tiny(**coaching):
    return parse_recipe(data(**coaching), "tiny")


# ----------------------------------------------------------------------------- the wrapper


def test_a_picked_proposal_runs_as_the_agents_step(spec):
    env, twin = CoachingWrapper(gym.make(IP), spec, **SHIELD), Coach(spec, load_model(IP))
    env.set_proposer(lambda obs, agent, proposal: True, until=0.5)
    obs, _ = env.reset(seed=2)
    for _ in range(30):
        twin.reset(obs)
        expected = np.clip(twin.act(obs), -3, 3)
        obs, _, terminated, truncated, info = env.step(np.array([2.5], dtype=np.float32))
        assert info["proposing"] and info["proposal_taken"]
        np.testing.assert_allclose(info["executed_action"], expected, rtol=1e-6)
        twin.reset(obs)
        np.testing.assert_allclose(info["next_proposal"], np.clip(twin.act(obs), -3, 3))
        assert info["coach_steps"] == 0  # the coach's action ran as the agent's step
        if terminated or truncated:
            obs, _ = env.reset()
    assert env.total_proposals_taken == 30 and env.total_agent_steps == 30


def test_a_judge_that_never_picks_changes_nothing_and_the_proposals_end(spec):
    env, plain = CoachingWrapper(gym.make(IP), spec, **SHIELD), CoachingWrapper(gym.make(IP), spec, **SHIELD)
    env.set_proposer(lambda obs, agent, proposal: False, until=0.5)
    env.reset(seed=7)
    plain.reset(seed=7)
    rng = np.random.default_rng(3)
    for _ in range(100):
        a = rng.uniform(-3, 3, 1).astype(np.float32)
        out, same = env.step(a), plain.step(a)
        np.testing.assert_array_equal(out[0], same[0])
        assert out[4]["proposing"] and not out[4]["proposal_taken"]
        if out[2] or out[3]:
            env.reset()
            plain.reset()
    env.set_progress(0.5)  # from until on the agent acts alone
    _, _, _, _, info = env.step(np.zeros(1, dtype=np.float32))
    assert "proposing" not in info and env.total_proposals_taken == 0


def test_the_wrapper_refuses_a_proposer_it_cannot_run(spec):
    with pytest.raises(CoachingError, match="needs a coach"):
        CoachingWrapper(gym.make(IP), None).set_proposer(lambda *a: True)
    with pytest.raises(CoachingError, match=r"expected \(obs, action, proposal\) -> bool"):
        CoachingWrapper(gym.make(IP), spec, **SHIELD).set_proposer(3)
    for until in (0.0, 1.5, float("nan"), True):
        with pytest.raises(CoachingError, match=r"expected a fraction of the budget in \(0, 1\]"):
            CoachingWrapper(gym.make(IP), spec, **SHIELD).set_proposer(lambda *a: True, until)


# ----------------------------------------------------------------------------- the target


class _Critics:
    """Two target critics with known values: Q1 = sum(a) + 1, Q2 = sum(a) (per row)."""

    q_networks = (None, None)

    def __call__(self, obs, actions):
        q = actions.sum(dim=1, keepdim=True)
        return q + 1.0, q

    def parameters(self):
        return iter(())


def test_the_target_answers_the_better_of_the_two_actions_hand_computed():
    stash = _Stash()
    stash.proposals = torch.tensor([[0.5], [-0.5], [0.2]])
    target = ProposalTarget(_Critics(), stash)
    answers = target(torch.zeros(3, 4), torch.tensor([[0.1], [0.3], [0.2]]))
    # min over the twins is sum(a); the better of actor 0.1 / proposal 0.5 is 0.5, then 0.3, then 0.2
    assert len(answers) == 2
    for a in answers:
        assert a.flatten().tolist() == pytest.approx([0.5, 0.3, 0.2])


# ----------------------------------------------------------------------------- a run


@pytest.fixture(scope="module")
def run(tmp_path_factory, spec):
    folder = tmp_path_factory.mktemp("ibrl") / "run"
    result = train(tiny(), spec, folder, progress_bar=False)
    return folder, result


def test_the_buffer_holds_the_actions_that_ran_and_the_next_proposals(run, spec):
    folder, result = run
    summary = read_json(folder / "summary.json")
    assert result.completed and summary["proposals_taken"] > 0
    checkpoint = latest_checkpoint(folder)
    buffer = _read_npz(checkpoint / "replay_buffer.npz")
    proposals = _read_npz(checkpoint / "proposals.npz")["next_proposals"]
    assert proposals.shape[0] == len(buffer["rewards"])
    assert np.all(np.abs(proposals) <= 1.0) and np.any(proposals != 0.0)
    # the stored next proposal is the coach's from the stored next observation (one env: row i)
    twin = Coach(spec, load_model(IP))
    for i in (0, len(proposals) // 2, len(proposals) - 1):
        next_obs = buffer["next_observations"][i, 0]
        twin.reset(next_obs)
        np.testing.assert_allclose(proposals[i], np.clip(twin.act(next_obs), -3, 3) / 3, rtol=1e-5, atol=1e-6)


def test_the_model_archive_does_not_hold_the_proposals_again(run):
    import json
    import zipfile

    folder, _ = run
    with zipfile.ZipFile(latest_checkpoint(folder) / "model.zip") as z:
        assert "next_proposals" not in json.loads(z.read("data"))  # they are in proposals.npz


def test_a_resume_restores_the_proposals(run, spec, tmp_path):
    folder, _ = run
    copy = tmp_path / "copy"
    shutil.copytree(folder, copy)
    checkpoint = latest_checkpoint(copy)
    stored = _read_npz(checkpoint / "proposals.npz")["next_proposals"]
    recipe = tiny()
    venv = make_vec_env(recipe, spec)
    model, _, _ = load_checkpoint(checkpoint, recipe, venv)
    np.testing.assert_array_equal(model.next_proposals[: len(stored)], stored)
    venv.close()
    extended = resume(copy, steps=600, progress_bar=False)
    assert extended.completed and read_json(copy / "summary.json")["proposals_taken"] >= 0


# ----------------------------------------------------------------------------- bad input


def test_the_field_reads_writes_and_refuses_bad_values():
    assert parse_coaching({"proposer": {}}).proposer == Proposer(0.5)
    assert parse_recipe(recipe_to_dict(tiny()), "again").coaching.proposer == Proposer(0.8)
    for value in (0, 1.5, -1, "half"):
        with pytest.raises(RecipeError, match="coaching.proposer.until"):
            parse_coaching({"proposer": {"until": value}})


@pytest.mark.parametrize(
    ("change", "coach", "message"),
    [
        ({"algo": "ppo"}, True, "use algo = 'sac'"),
        ({}, False, "this run has no coach"),
        ({"n_envs": 2}, True, "use n_envs = 1"),
        ({"coaching": {"coach_buffer": {"share": 0.5}}}, True, "coaching.proposer and coaching.coach_buffer"),
        ({"coaching": {"value_trigger": {"margin": 1.0}}}, True, "coaching.proposer and coaching.value_trigger"),
    ],
)
def test_it_is_refused_where_it_cannot_propose(spec, change, coach, message):
    with pytest.raises(CoachingError) as info:
        check_couplings(changed_recipe(tiny(), change), spec if coach else None)
    assert message in str(info.value)


def test_a_proposer_with_no_coach_is_one_line_and_exit_2(tmp_path):
    path = tmp_path / "r.toml"
    path.write_text(tomli_w.dumps(data()))
    code, stderr = cli_in_process("train", IP, "--coach", "none", "--recipe", str(path), "--run-dir",
                                  str(tmp_path / "run"))  # fmt: skip
    lines = stderr.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "coaching.proposer" in lines[0] and "no coach" in lines[0], stderr
    assert not (tmp_path / "run").exists()
