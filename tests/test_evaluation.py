"""Agent-alone evaluation: episodes run side by side give the returns of the same episodes run alone.

Real MuJoCo envs and real SB3 policies (untrained: the mechanics, not what was learned).
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from stable_baselines3 import PPO, SAC

from pidlab.rl.evaluation import MAX_BATCH, batch_invariant, evaluate_agent, evaluation_envs, sb3_policy

SEEDS = list(range(1000000, 1000008))


def _normalizer(env_id: str, seed: int = 0):
    """Fixed affine observation statistics, as a frozen VecNormalize would apply them."""
    n = gym.make(env_id).observation_space.shape[0]
    rng = np.random.default_rng(seed)
    mean, scale = rng.normal(0, 0.1, n), rng.uniform(0.5, 2.0, n)
    return lambda obs: np.clip((obs - mean) / scale, -10.0, 10.0)


@pytest.mark.parametrize(
    ("cls", "env_id", "kwargs"),
    [
        (PPO, "InvertedPendulum-v5", {}),
        (PPO, "Hopper-v5", {"policy_kwargs": {"net_arch": [64, 64]}}),
        (SAC, "InvertedPendulum-v5", {"use_sde": True}),
    ],
)
def test_side_by_side_equals_one_by_one(cls, env_id, kwargs):
    torch.set_num_threads(1)  # as the trainer runs it
    model = cls("MlpPolicy", env_id, seed=3, device="cpu", **kwargs)
    policy = sb3_policy(model, _normalizer(env_id))
    alone = evaluate_agent(policy, gym.make(env_id), SEEDS)
    together = evaluate_agent(policy, evaluation_envs(env_id, len(SEEDS)), SEEDS)
    in_waves = evaluate_agent(policy, evaluation_envs(env_id, 3), SEEDS)  # 3 + 3 + 3 + 1
    assert together == alone == in_waves  # returns and lengths, bit for bit
    if env_id == "Hopper-v5":  # episodes of different lengths: the batch shrank as they ended
        assert len(set(alone.lengths)) > 1


def test_equals_sb3_predict_one_observation_at_a_time():
    """Side by side gives the actions, and returns, of SB3's predict on one observation at a time."""
    for cls, env_id, kwargs in [(PPO, "Hopper-v5", {}), (SAC, "Hopper-v5", {"use_sde": True})]:
        model = cls("MlpPolicy", env_id, seed=5, device="cpu", **kwargs)
        obs = np.random.default_rng(1).normal(size=(64, 11)).astype(np.float32)
        theirs = np.stack([model.predict(o, deterministic=True)[0] for o in obs])
        assert np.array_equal(sb3_policy(model)(obs), theirs)
    ip = PPO("MlpPolicy", "InvertedPendulum-v5", seed=5, device="cpu")

    def predict_one_by_one(batch: np.ndarray) -> np.ndarray:
        return np.stack([ip.predict(o, deterministic=True)[0] for o in batch])

    env = gym.make("InvertedPendulum-v5")
    ours = evaluate_agent(sb3_policy(ip), evaluation_envs("InvertedPendulum-v5", 4), SEEDS[:4])
    assert ours == evaluate_agent(predict_one_by_one, env, SEEDS[:4])


def test_rows_do_not_depend_on_the_batch():
    model = PPO("MlpPolicy", "Hopper-v5", seed=2, device="cpu", policy_kwargs={"net_arch": [256, 256]})
    frozen = batch_invariant(model.policy)
    x = torch.as_tensor(np.random.default_rng(0).normal(size=(100, 11)).astype(np.float32))
    with torch.inference_mode():
        full = frozen._predict(x, deterministic=True)
        for rows in (slice(0, 1), slice(3, 10), slice(40, 100)):
            assert torch.equal(frozen._predict(x[rows], deterministic=True), full[rows])
        # the plain policy does not have that property on this machine's BLAS, which is why the copy exists
        plain = model.policy._predict(x, deterministic=True)
    assert torch.allclose(plain, full, atol=1e-5)


def test_the_copy_is_frozen_when_taken():
    model = PPO("MlpPolicy", "InvertedPendulum-v5", seed=0, device="cpu")
    policy = sb3_policy(model)
    obs = np.zeros((1, 4), dtype=np.float32) + 0.1
    before = policy(obs).copy()
    with torch.no_grad():
        for p in model.policy.parameters():
            p.add_(1.0)  # the agent trains on
    assert np.array_equal(policy(obs), before)
    assert not np.array_equal(sb3_policy(model)(obs), before)


def test_evaluation_envs_are_capped():
    assert len(evaluation_envs("InvertedPendulum-v5", 2)) == 2
    assert len(evaluation_envs("InvertedPendulum-v5", 500)) == MAX_BATCH
    result = evaluate_agent(lambda obs: np.zeros((len(obs), 1)), gym.make("InvertedPendulum-v5"), [7])
    assert result.env_steps == sum(result.lengths) == result.lengths[0] > 0
