"""Coach demonstrations: the coach acts on the training envs, with noise, before the agent does.

The demonstrations run on the run's own training envs (:meth:`CoachingWrapper.demonstrate`), so
every demonstration step is an env step of the run: it is charged to the budget, its episodes are
logged in ``episodes.csv`` like any other (agent steps 0), a termination is a fall, and the
observation normalizer sees the states. Noise on the coach's action (DART, Laskey et al. 2017)
makes the demonstrations cover the states the coach corrects from, not only its nominal path.

The file ``demonstrations.npz`` of a run holds them (plain arrays, read with
``allow_pickle=False``): ``obs`` (raw observations the coach acted on), ``actions`` (the executed,
noisy actions), ``rewards`` (raw env rewards), ``terminated``, ``truncated``, ``env_index`` and
``next_obs`` (the raw observation the step led to: the episode's last one where it ended), one row
per demonstration step in the order the envs took them. Files written before ``next_obs`` was kept
load without it (``next_obs`` None).

An off-policy agent with a coach buffer (SAC, :class:`pidlab.rl.replay.CoachReplaySAC`) keeps every
demonstration step there as a transition of the coach's
(:meth:`~pidlab.rl.replay.CoachReplaySAC.keep_demonstrations`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pidlab.errors import CoachingError
from pidlab.files import atomic_write_bytes, open_binary

FILE = "demonstrations.npz"
FIELDS = ("obs", "actions", "rewards", "terminated", "truncated", "env_index")
"""The arrays every demonstrations file holds."""
OPTIONAL = ("next_obs",)
"""The arrays a file written since they were kept holds too."""


@dataclass(frozen=True)
class Demonstrations:
    """Demonstration steps, one row each.

    Attributes
    ----------
    obs : ndarray, shape (n, obs_dim)
        Raw observation the coach acted on.
    actions : ndarray, shape (n, act_dim)
        The executed action (coach action plus noise, clipped to the action space).
    rewards : ndarray, shape (n,)
        Raw env reward of the step.
    terminated, truncated : ndarray of bool, shape (n,)
        How the step ended its episode (both False: the episode went on).
    env_index : ndarray of int, shape (n,)
        Which training env took the step.
    next_obs : ndarray, shape (n, obs_dim), or None
        Raw observation the step led to (where it ended an episode, that episode's last one); None
        for a file written before it was kept.
    """

    obs: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    env_index: np.ndarray
    next_obs: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.rewards.shape[0])


def collect(venv: Any, steps: int, noise: float, seed: int, on_step: Any) -> tuple[Demonstrations, Any, Any]:
    """Run the coach with noise on every env of ``venv`` for at least ``steps`` env steps.

    Parameters
    ----------
    venv : VecEnv
        The training envs (a ``VecNormalize`` on top is used as is: it learns the obs statistics),
        each a :class:`pidlab.rl.coaching.CoachingWrapper` under SB3's Monitor.
    steps : int
        Env steps to demonstrate (the last round of ``n_envs`` steps may pass it).
    noise : float
        Noise on the coach's action, a fraction of half the action range.
    seed : int
        Env ``i`` draws its noise with seed ``seed + i``.
    on_step : callable
        Called with each round's ``infos`` and whether steps remain (the trainer's accounts).

    Returns
    -------
    demos : Demonstrations
    last_obs, last_dones : ndarray
        What the envs returned last (normalized as the agent sees it), so that learning goes on
        from there without resetting them.
    """
    n = venv.num_envs
    for i in range(n):
        venv.env_method("demonstrate", noise, seed + i, indices=[i])
    rows: dict[str, list[Any]] = {k: [] for k in FIELDS + OPTIONAL}
    obs = _raw(venv, venv.reset())
    zeros = np.zeros((n, *venv.action_space.shape), dtype=venv.action_space.dtype)
    done, new_obs, dones = 0, None, np.zeros(n, dtype=bool)
    try:
        while done < steps:
            new_obs, _, dones, infos = venv.step(zeros)
            raw_new = _raw(venv, new_obs)
            for i, info in enumerate(infos):
                ended = bool(dones[i])
                rows["obs"].append(obs[i])
                rows["next_obs"].append(_terminal(venv, info) if ended else raw_new[i])
                rows["actions"].append(np.asarray(info["demonstration_action"], dtype=np.float32))
                rows["rewards"].append(float(info.get("coach_reward", 0.0)))
                fell = bool(info.get("fell", False))
                rows["terminated"].append(fell)
                rows["truncated"].append(ended and not fell)
                rows["env_index"].append(i)
            done += n
            on_step(infos, done < steps)
            obs = raw_new
    finally:
        venv.env_method("demonstrate", None)
    demos = Demonstrations(
        obs=np.asarray(rows["obs"], dtype=np.float32),
        actions=np.asarray(rows["actions"], dtype=np.float32),
        rewards=np.asarray(rows["rewards"], dtype=np.float64),
        terminated=np.asarray(rows["terminated"], dtype=bool),
        truncated=np.asarray(rows["truncated"], dtype=bool),
        env_index=np.asarray(rows["env_index"], dtype=np.int64),
        next_obs=np.asarray(rows["next_obs"], dtype=np.float32),
    )
    return demos, new_obs, np.asarray(dones, dtype=bool)


def _terminal(venv: Any, info: dict[str, Any]) -> np.ndarray:
    """The raw last observation of an episode that ended (SB3 keeps it in the step's info).

    A ``VecNormalize`` normalized it there; it is unnormalized as SB3's off-policy agents do.
    """
    last = np.asarray(info["terminal_observation"])
    if getattr(venv, "norm_obs", False):
        last = venv.unnormalize_obs(last)
    return np.asarray(last, dtype=np.float32)


def _raw(venv: Any, obs: np.ndarray) -> np.ndarray:
    """The raw observations of the last step or reset (before a VecNormalize's normalization)."""
    original = getattr(venv, "get_original_obs", None)
    return np.array(original() if original is not None else obs, dtype=np.float32)


def save(path: str | Path, demos: Demonstrations) -> Path:
    """Write ``demos`` to ``path`` (an ``.npz`` of plain arrays), atomically."""
    import io

    buf = io.BytesIO()
    arrays = {k: getattr(demos, k) for k in FIELDS + OPTIONAL if getattr(demos, k) is not None}
    np.savez(buf, **arrays)
    atomic_write_bytes(Path(path), buf.getvalue())
    return Path(path)


def load(path: str | Path) -> Demonstrations:
    """Read demonstrations written by :func:`save` (no pickled object is ever loaded).

    Raises
    ------
    CoachingError
        The file is missing a field, holds objects, or its arrays disagree in length.
    """
    try:
        with open_binary(path) as fh, np.load(fh, allow_pickle=False) as data:
            arrays = {k: np.asarray(data[k]) for k in FIELDS + tuple(k for k in OPTIONAL if k in data)}
    except (OSError, KeyError, ValueError) as exc:
        raise CoachingError(f"{path}: not a demonstrations file ({exc})") from None
    n = arrays["rewards"].shape[0]
    if (
        any(a.shape[0] != n for a in arrays.values())
        or arrays["obs"].ndim != 2
        or arrays["actions"].ndim != 2
        or ("next_obs" in arrays and arrays["next_obs"].shape != arrays["obs"].shape)
    ):
        raise CoachingError(f"{path}: its arrays disagree in length or shape")
    return Demonstrations(**arrays)
