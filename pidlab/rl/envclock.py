"""SAC in a coached run counts env steps, the coach's included (``learning_starts`` among them).

SB3 adds one to ``num_timesteps`` per agent action. In a coached run that is not the run's clock:
a takeover's coach steps and a roll-in's are env steps that SB3 never sees, and a vetoed agent
action ran no env step at all. The run's budget, its evaluations and the coach's schedules count
env steps (:meth:`pidlab.rl.train._Trainer.on_step`); SAC's ``learning_starts`` (its random
warm-up, and when its critic may first judge a value trigger or a proposal) counted agent actions,
so under a shield that runs most of the early env steps learning started late. On
InvertedPendulum with ``rescue-propose`` (seed 0) the shield ran 74 % of the first 15,000 env
steps, in which the agent acted 3,907 times and SAC made no gradient step; at that rate its
10,000th action comes near 38,000 env steps, after the proposals end (25,000).

:class:`CoachedSAC` moves ``num_timesteps`` to the run's env steps after every step
(:func:`pidlab.rl.coaching.uncounted_env_steps`), so that ``learning_starts`` counts env steps
whichever actor made them, as the coach buffer already does (:mod:`pidlab.rl.replay`). The
gradient steps are still SB3's: one per ``train_freq`` agent actions at the recipe's rate (a coach
buffer adds the coach steps' own). Without a coach nothing changes: every env step is an agent
action.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from stable_baselines3 import SAC

from pidlab.rl.coaching import uncounted_env_steps


class CoachedSAC(SAC):
    """SAC whose ``num_timesteps`` is the run's env steps (module docstring)."""

    def _store_transition(self, replay_buffer: Any, buffer_action: np.ndarray, new_obs: Any,
                          reward: np.ndarray, dones: np.ndarray,
                          infos: list[dict[str, Any]]) -> None:  # fmt: skip
        super()._store_transition(replay_buffer, buffer_action, new_obs, reward, dones, infos)
        self.num_timesteps += uncounted_env_steps(infos)
