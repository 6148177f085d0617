"""The fading blend: what runs, what the agent's transition holds, and that the coach's weight ends at 0."""

from __future__ import annotations

import json
from pathlib import Path

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
from pidlab.rl.recipe import load_recipe, parse_recipe
from pidlab.rl.schedule import Schedule
from pidlab.rl.train import train
from tests.helpers import ROOT, TUNING

IP = "InvertedPendulum-v5"
FADE = {"shape": "linear", "start": 0.8, "end": 0.0, "begin": 0.0, "finish": 0.5}


def _data(steps: int, coaching: dict) -> dict:
    data = tomllib.loads((ROOT / "coach" / f"{IP}.toml").read_text())
    data["steps"] = steps
    data["evaluation"] = {"every": 1000, "episodes": 2, "seed": 1000000}
    data["coaching"] = {**data["coaching"], "off_after": 0.0, **coaching}
    return data


@pytest.mark.parametrize(
    ("blend", "message"),
    [
        (0.5, "must fade to 0"),
        ({"shape": "linear", "start": 1.5, "end": 0.0}, "cannot exceed 1"),
        ({"shape": "linear", "start": 0.8, "end": 0.1}, "must fade to 0"),
        ({"shape": "linear", "start": -0.2, "end": 0.0}, "coaching.blend"),
    ],
)
def test_a_blend_that_does_not_fade_to_zero_is_refused(blend, message: str) -> None:
    with pytest.raises(RecipeError, match="coaching.blend") as err:
        parse_recipe(_data(1000, {"blend": blend}))
    assert message in str(err.value)


def test_the_executed_action_is_the_blend_and_the_agent_keeps_its_own() -> None:
    spec = load_spec(TUNING / f"{IP}.pidlab-rescue.toml")
    w = 0.3
    env = CoachingWrapper(gym.make(IP), spec, off_after=0.0, blend=Schedule("constant", w, w))
    twin = Coach(spec, load_model(IP))  # replays the blend's coach on the same observations
    obs, _ = env.reset(seed=4)
    twin.reset(obs)
    rng = np.random.default_rng(0)
    for _ in range(50):
        action = rng.uniform(-3, 3, size=1).astype(np.float32)
        expected = np.clip(w * twin.act(obs) + (1 - w) * action, -3, 3)
        obs, _, terminated, truncated, info = env.step(action)
        np.testing.assert_allclose(info["executed_action"], expected, rtol=1e-5, atol=1e-6)
        assert info["blend_weight"] == w and info["coach_steps"] == 0 and not info["intervened"]
        if terminated or truncated:
            obs, _ = env.reset()
            twin.reset(obs)
    # at weight 0 the agent's action runs unchanged
    env.blend = Schedule("constant", 0.0, 0.0)
    env.reset(seed=5)
    _, _, _, _, info = env.step(np.array([0.7], dtype=np.float32))
    assert info["executed_action"][0] == pytest.approx(0.7) and info["blend_weight"] == 0.0
    with pytest.raises(CoachingError, match="needs a coach"):
        CoachingWrapper(gym.make(IP), None, blend=Schedule("constant", w, w))


def test_a_blended_run_ends_with_the_agent_alone(tmp_path: Path) -> None:
    from dataclasses import replace

    path = tmp_path / "blend.toml"
    path.write_text(tomli_w.dumps(_data(2000, {"blend": FADE})))
    spec = load_spec(TUNING / f"{IP}.pidlab-rescue.toml")
    with pytest.raises(CoachingError, match="coaching.blend with algo = 'sac'"):
        train(replace(load_recipe(path), algo="sac"), spec, tmp_path / "sac", progress_bar=False)
    assert not (tmp_path / "sac").exists()
    result = train(load_recipe(path), spec, tmp_path / "run", progress_bar=False)
    s = json.loads((tmp_path / "run" / "summary.json").read_text())
    # every step is the agent's (blended, not taken over): no coach step, no intervention
    assert result.completed and s["coach_steps"] == 0 and s["interventions"] == 0
    assert s["env_steps"] == s["agent_steps"] >= 2000
    assert Schedule(**FADE)(1.0) == 0.0 and Schedule(**FADE)(0.5) == 0.0 and Schedule(**FADE)(0.25) == 0.4


# ------------------------------------------------------------------------------- residual


@pytest.mark.parametrize(
    ("coaching", "message"),
    [
        ({"residual": 1.0}, "coaching.residual: the coach's weight must fade to 0"),
        ({"residual": {"shape": "linear", "start": 1.2, "end": 0.0}}, "coaching.residual: the coach's weight cannot"),
        ({"residual": FADE, "blend": FADE}, "coaching.residual and blend: both mix"),
    ],
)
def test_a_residual_that_cannot_end_with_the_agent_alone_is_refused(coaching: dict, message: str) -> None:
    with pytest.raises(RecipeError, match="coaching") as err:
        parse_recipe(_data(1000, coaching))
    assert message in str(err.value)


def test_the_residual_adds_the_agents_correction_to_the_weighted_coach() -> None:
    spec = load_spec(TUNING / f"{IP}.pidlab-rescue.toml")
    w = 0.6
    env = CoachingWrapper(gym.make(IP), spec, off_after=0.0, blend=Schedule("constant", w, w), residual=True)
    twin = Coach(spec, load_model(IP))
    obs, _ = env.reset(seed=4)
    twin.reset(obs)
    rng = np.random.default_rng(1)
    clipped = 0
    for _ in range(60):
        action = rng.uniform(-3, 3, size=1).astype(np.float32)
        raw = w * twin.act(obs) + action
        clipped += int(np.any(np.abs(raw) > 3))
        obs, _, terminated, truncated, info = env.step(action)
        np.testing.assert_allclose(info["executed_action"], np.clip(raw, -3, 3), rtol=1e-5, atol=1e-6)
        assert info["blend_weight"] == w and info["coach_steps"] == 0
        if terminated or truncated:
            obs, _ = env.reset()
            twin.reset(obs)
    assert clipped > 0  # the clip to the actuator's range was exercised
    # a zero correction at weight 1 runs the coach's own action
    env.blend = Schedule("constant", 1.0, 1.0)
    obs, _ = env.reset(seed=6)
    twin.reset(obs)
    expected = twin.act(obs)
    _, _, _, _, info = env.step(np.zeros(1, dtype=np.float32))
    np.testing.assert_allclose(info["executed_action"], expected, rtol=1e-5, atol=1e-6)
    with pytest.raises(CoachingError, match="expected a weight"):
        CoachingWrapper(gym.make(IP), spec, residual=True)


def test_a_residual_run_ends_with_the_agent_alone_and_needs_ppo_and_a_coach(tmp_path: Path) -> None:
    from dataclasses import replace

    path = tmp_path / "residual.toml"
    path.write_text(tomli_w.dumps(_data(2000, {"residual": FADE})))
    recipe = load_recipe(path)
    spec = load_spec(TUNING / f"{IP}.pidlab-rescue.toml")
    with pytest.raises(CoachingError, match="no coach"):
        train(recipe, None, tmp_path / "none", progress_bar=False)
    with pytest.raises(CoachingError, match="coaching.residual with algo = 'sac'"):
        train(replace(recipe, algo="sac"), spec, tmp_path / "sac", progress_bar=False)
    assert not (tmp_path / "none").exists() and not (tmp_path / "sac").exists()
    result = train(recipe, spec, tmp_path / "run", progress_bar=False)
    s = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert result.completed and s["coach_steps"] == 0 and s["interventions"] == 0
    assert s["env_steps"] == s["agent_steps"] >= 2000
    saved = tomllib.loads((tmp_path / "run" / "config.toml").read_text())
    coaching = saved["recipe"]["coaching"]
    assert coaching["residual"]["start"] == 0.8 and "blend" not in coaching
