"""SAC's clock in a coached run is the run's env steps (pidlab/rl/envclock.py).

Hand-computed cases for the count, and short coached SAC runs (a few hundred env steps, a small
network) whose ``num_timesteps`` must equal the env steps of their accounts, with SAC's first
gradient step after ``learning_starts`` env steps. Mechanics, not luck.
"""

from __future__ import annotations

import pytest

from pidlab.controller.spec import load_spec
from pidlab.files import read_json
from pidlab.rl.coaching import step_env_steps, uncounted_env_steps
from pidlab.rl.recipe import parse_recipe
from pidlab.rl.rundir import latest_checkpoint
from pidlab.rl.train import train
from tests.helpers import TUNING, sac_recipe_data

IP = "InvertedPendulum-v5"


@pytest.mark.parametrize(
    ("info", "agent", "coach"),
    [
        ({}, 1, 0),  # an agent action, no coach
        ({"coach_steps": 3}, 1, 3),  # the action ran, then a takeover of 3 coach steps
        ({"vetoed": True, "coach_steps": 5}, 0, 5),  # vetoed: it never ran; the coach ran 5
        ({"demonstration": True, "coach_steps": 1}, 0, 1),  # a demonstration step is the coach's
    ],
)
def test_the_env_steps_of_one_step_by_hand(info, agent, coach):
    assert step_env_steps(info) == (agent, coach)


def test_what_sb3s_count_misses_by_hand():
    # SB3 counted one per env; the runs were 1, 1 + 3, 0 + 5, and 1 after a roll-in of 7 coach steps
    infos = [{}, {"coach_steps": 3}, {"vetoed": True, "coach_steps": 5}, {"rollin": {"steps": 7}}]
    assert [uncounted_env_steps([i]) for i in infos] == [0, 3, 4, 7]
    assert uncounted_env_steps(infos) == 14


@pytest.fixture(scope="module")
def spec():
    return load_spec(TUNING / f"{IP}.pidlab-rescue.toml")


@pytest.mark.parametrize("coaching", [{}, {"proposer": {"until": 0.8}}], ids=["shield", "proposer"])
def test_a_coached_sac_run_counts_env_steps(coaching, spec, tmp_path):
    recipe = parse_recipe(sac_recipe_data(**coaching), "tiny")  # learning_starts 100, 400 env steps
    folder = tmp_path / "run"
    result = train(recipe, spec, folder, progress_bar=False)
    state = read_json(latest_checkpoint(folder) / "state.json")
    assert result.completed and result.coach_steps > 0  # the shield ran env steps SB3 never saw
    assert state["num_timesteps"] == state["env_steps"] == result.env_steps
    assert result.agent_steps < result.env_steps
    # SB3 trains 8 gradient steps per rollout of 8 agent actions once num_timesteps passed
    # learning_starts: at most one per agent action, and some, since 100 env steps came early
    assert 0 < state["policy_updates"] <= result.agent_steps + 8
    assert state["policy_updates"] % 8 == 0
