"""The coaching wrapper of a recipe's ``[coaching]`` table, as pidlab's trainer and ``coach_env`` build it.

:func:`wrapper_arguments` turns a :class:`~pidlab.rl.recipe.Coaching` into the
:class:`~pidlab.rl.coaching.CoachingWrapper`'s arguments; the trainer's envs and
:func:`pidlab.experiment.coach_env.coach_env` (your own training loop) both call it, so the two
wrap an env the same way.
"""

from __future__ import annotations

from typing import Any

from pidlab.rl.recipe import Coaching

TRAINER_ONLY = ("demonstrations", "warm_start", "rollin")
"""Coaching fields that need pidlab's trainer, not only the env (:func:`pidlab.coach_env` refuses them)."""


def mix_of(c: Coaching) -> Any:
    """The coach's weight in the executed action: the blend's or the residual's (None: neither)."""
    return c.blend if c.blend is not None else c.residual


def wrapper_arguments(c: Coaching, coached: bool) -> dict[str, Any]:
    """The :class:`~pidlab.rl.coaching.CoachingWrapper` arguments of ``c`` (``coached``: a coach is given)."""
    return {
        "mode": c.mode, "region": c.region, "trigger": c.trigger, "predictor": c.predictor,
        "nudge_steps": c.nudge_steps,
        "max_coach_steps": c.max_coach_steps, "reward": c.reward, "probability": c.probability,
        "width": c.width, "off_after": c.off_after, "view": c.view, "cost": c.cost, "handback": c.handback,
        "blend": mix_of(c) if coached else None, "residual": c.residual is not None and coached,
        "record": c.coach_buffer is not None and coached,
    }  # fmt: skip
