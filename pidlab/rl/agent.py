"""A finished run's agent, loaded without unpickling anything: to act, to evaluate, to deploy.

:func:`load_agent` is the trusted way to use what ``pidlab train`` produced. It rebuilds the agent
from the run's ``config.toml`` (its recipe), reads the weights from ``final_model.zip`` and the
normalizer statistics from ``final_vecnormalize.npz`` (see :mod:`pidlab.rl.checkpoint`), each
checked against the SHA-256 that ``summary.json`` records::

    agent = pidlab.load_agent("runs/InvertedPendulum-v5/none-ppo-seed0")
    action = agent.act(obs)          # deterministic, observation normalized as in training
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from pidlab.errors import RunDirError
from pidlab.files import load_json
from pidlab.rl.checkpoint import FINAL, check_manifest, expected_files, load_agent_files
from pidlab.rl.recipe import Recipe
from pidlab.rl.rundir import load_run_config


@dataclass(frozen=True)
class TrainedAgent:
    """A trained agent and the observation normalization it was trained with.

    Attributes
    ----------
    recipe : Recipe
        The run's recipe.
    model : stable_baselines3.common.base_class.BaseAlgorithm
        The SB3 agent (no replay buffer).
    obs_mean, obs_var : ndarray, shape (n_obs,) or None
        The normalizer's running statistics (None: observations were not normalized).
    clip_obs, epsilon : float
        The normalizer's clip range and variance floor.
    """

    recipe: Recipe
    model: Any
    obs_mean: np.ndarray | None
    obs_var: np.ndarray | None
    clip_obs: float
    epsilon: float

    def normalize(self, obs: np.ndarray) -> np.ndarray:
        """``obs`` as the agent saw it in training (``VecNormalize.normalize_obs``)."""
        if self.obs_mean is None or self.obs_var is None:
            return np.asarray(obs)
        z = (np.asarray(obs) - self.obs_mean) / np.sqrt(self.obs_var + self.epsilon)
        return np.clip(z, -self.clip_obs, self.clip_obs)

    def act(self, obs: np.ndarray) -> np.ndarray:
        """The agent's deterministic action for one observation, shape (n_obs,), or a batch."""
        from pidlab.rl.evaluation import sb3_policy

        x = np.asarray(obs, dtype=np.float64)
        actions = sb3_policy(self.model, self.normalize)(x.reshape(-1, x.shape[-1]))
        return actions[0] if x.ndim == 1 else actions


def load_agent(run_dir: str | Path) -> TrainedAgent:
    """The final agent of a finished run, its files checked against ``summary.json``'s digests.

    Parameters
    ----------
    run_dir : path
        A run folder whose budget was spent (``pidlab train`` wrote ``final_model.zip``).

    Returns
    -------
    TrainedAgent

    Raises
    ------
    RunDirError
        Not a run folder, a run that has not finished, or a final file that is missing, whose
        digest does not match, or that is not this run's agent (the message names it).
    """
    from stable_baselines3.common.vec_env import VecNormalize

    from pidlab.rl.train import make_vec_env, new_model

    if not isinstance(run_dir, (str, Path)) or str(run_dir) == "":
        raise RunDirError(f"run_dir={run_dir!r}: expected the path of a run folder", param="run_dir")
    run_dir = Path(run_dir)
    recipe, _, _ = load_run_config(run_dir)
    record = run_dir / "summary.json"
    summary = load_json(record, "run summary", RunDirError) if record.is_file() else None
    if not isinstance(summary, dict) or not summary.get("completed"):
        raise RunDirError(f"{run_dir}: the run has not finished (no final agent); resume it first")
    single = replace(recipe, vec_env="dummy")  # its normalizer holds one return per env
    venv = make_vec_env(single, None)
    try:
        files = check_manifest(summary, record, expected_files(False, isinstance(venv, VecNormalize)))
        agent = load_agent_files(run_dir, files, record, lambda v: new_model(single, v), venv, names=FINAL)
    finally:
        venv.close()
    norm = agent.venv if isinstance(agent.venv, VecNormalize) and agent.venv.norm_obs else None
    if norm is None:
        return TrainedAgent(recipe, agent.model, None, None, np.inf, 0.0)
    rms: Any = norm.obs_rms  # one RunningMeanStd (pidlab's observations are arrays, not dicts)
    mean, var = np.array(rms.mean), np.array(rms.var)
    return TrainedAgent(recipe, agent.model, mean, var, float(norm.clip_obs), float(norm.epsilon))
