"""A Gymnasium MuJoCo env made from an MJCF file and its model card: your robot, trainable.

:class:`CardEnv` is the env a model card describes: its observation is the card's observation map
(:func:`pidlab.plant.observation.observe`), an episode ends when the card's termination rule says
so (:func:`pidlab.plant.observation.check_termination`), and it pays the card's ``[reward] alive``
(1 when not given) per step that does not fail and 0 on a step that does (a failing step's reward
terms are ``[]``). Episodes start at the card's operating point, each ``qpos`` and ``qvel`` entry
moved by a uniform draw in ``±reset_noise_scale``, as Gymnasium's InvertedPendulum does.

Register it under an id of your own (``pidlab init`` writes the module that does)::

    gymnasium.register("MyCartPole-v0", entry_point="pidlab.plant.card_env:CardEnv",
                       kwargs={"card": "models/MyCartPole-v0.toml"}, max_episode_steps=1000)

The card's ``[model]`` table names the MJCF file and the frame skip (or pass ``xml_file`` and
``frame_skip`` yourself).

Its reward is the simplest one a balancing task needs; for another task, subclass it and override
:meth:`CardEnv.reward` (and keep the card's ``[reward]`` facts true to it).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from gymnasium import spaces, utils
from gymnasium.envs.mujoco.mujoco_env import MujocoEnv

from pidlab.errors import ModelCardError
from pidlab.plant.card import ModelCard, load_card
from pidlab.plant.observation import check_termination, observe


class CardEnv(MujocoEnv, utils.EzPickle):
    """The env of an MJCF file and its model card (see the module docstring).

    Parameters
    ----------
    xml_file : str or Path, optional
        The MJCF file (default: the one the card's ``[model]`` table names).
    card : ModelCard or str or Path
        Its model card (or the card's file); required.
    frame_skip : int, optional
        MuJoCo steps per env step (the control period is ``frame_skip`` times the model's
        timestep); default: the card's ``[model] frame_skip``, else 1.
    reset_noise_scale : float
        Half-width of the uniform noise on the operating point at reset.
    **kwargs
        Passed to :class:`gymnasium.envs.mujoco.mujoco_env.MujocoEnv` (``render_mode``, ``width``...).

    Raises
    ------
    ModelCardError
        No card; no MJCF file given or named by the card; the card does not fit the model (a
        joint, site or actuator it names is missing, or its operating point has the wrong length).
    """

    metadata = {"render_modes": ["human", "rgb_array", "depth_array"]}  # noqa: RUF012 - Gymnasium's contract

    def __init__(
        self,
        xml_file: str | Path | None = None,
        card: ModelCard | str | Path | None = None,
        frame_skip: int | None = None,
        reset_noise_scale: float = 0.01,
        **kwargs: Any,
    ) -> None:
        utils.EzPickle.__init__(self, xml_file, card, frame_skip, reset_noise_scale, **kwargs)
        if card is None:
            raise ModelCardError("CardEnv needs its model card: card=PATH (or a ModelCard)")
        self.card = card if isinstance(card, ModelCard) else load_card(card)
        xml_file, frame_skip = _model_of(self.card, xml_file, frame_skip)
        self._reset_noise_scale = float(reset_noise_scale)
        size = len(self.card.observation)
        space = spaces.Box(low=-np.inf, high=np.inf, shape=(size,), dtype=np.float64)
        import mujoco

        model = mujoco.MjModel.from_xml_path(str(Path(xml_file).resolve()))
        fps = int(np.round(1.0 / (model.opt.timestep * frame_skip)))
        self.metadata = {**type(self).metadata, "render_fps": fps}
        MujocoEnv.__init__(self, str(Path(xml_file).resolve()), frame_skip, observation_space=space, **kwargs)
        self.card.check_against(self.model, frame_skip)
        op = self.card.operating_point
        self._qpos0 = np.asarray(op.qpos, dtype=float)
        self._qvel0 = np.asarray(op.qvel, dtype=float)
        if not self.card.observation:
            raise ModelCardError(f"{self.card.path}: no [[observation]]: the env needs at least one")

    def reward(self, terminated: bool) -> float:
        """The step's reward: the card's alive reward, 0 on a failing step (override for another task)."""
        alive = self.card.reward.alive
        return 0.0 if terminated else float(1.0 if alive is None else alive)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:  # type: ignore[override]
        """One control period: the action held for ``frame_skip`` MuJoCo steps."""
        self.do_simulation(action, self.frame_skip)
        obs = observe(self.card, self.model, self.data)
        terminated = check_termination(self.card, self.model, self.data).terminated
        if self.render_mode == "human":
            self.render()
        return obs, self.reward(terminated), terminated, False, {}

    def reset_model(self) -> np.ndarray:
        """The card's operating point with uniform noise (Gymnasium's ``reset`` calls it)."""
        s = self._reset_noise_scale
        qpos = self._qpos0 + self.np_random.uniform(-s, s, size=self.model.nq)
        qvel = self._qvel0 + self.np_random.uniform(-s, s, size=self.model.nv)
        self.set_state(qpos, qvel)
        return observe(self.card, self.model, self.data)


def _model_of(card: ModelCard, xml_file: str | Path | None, frame_skip: int | None) -> tuple[str, int]:
    """The MJCF file and frame skip of a card's env: the ones given, else the card's ``[model]``."""
    if xml_file is None:
        if card.model is None:
            raise ModelCardError(
                f"{card.path}: no [model] mjcf = ...; give CardEnv its MJCF file (xml_file=...) "
                "or name it in the card"
            )
        xml_file = card.model.mjcf
    if not Path(xml_file).is_file():
        raise ModelCardError(
            f"{card.path}: the MJCF file {str(xml_file)!r} does not exist; expected an existing .xml"
        )
    if frame_skip is None:
        frame_skip = card.model.frame_skip if card.model is not None else 1
    return str(xml_file), int(frame_skip)
