"""Coach your own training loop: your Gymnasium env, wrapped with a coach as one of pidlab's conditions.

Two lines, in a CleanRL-style loop or around SB3 directly::

    import pidlab
    env = pidlab.coach_env(gym.make("InvertedPendulum-v5"), "tuning/InvertedPendulum-v5.pidlab-rescue.toml")
    PPO("MlpPolicy", env).learn(50_000)

:func:`coach_env` reads a condition of the conditions file (default ``rescue-terminal``: the
rescue region's predictive veto, the agent's episode ends at a veto as a failure) and builds the
:class:`~pidlab.rl.coaching.CoachingWrapper` exactly as pidlab's trainer does for that condition
(:func:`pidlab.rl.wrap.wrapper_arguments`, which the trainer calls too). The couplings that live
in the env come with it: the takeovers and vetoes with their views, blends and residuals. Those
that need the trainer (demonstrations, warm starts, roll-ins) do not, and a condition with one is
refused. Schedules (``probability``, ``width``, ``off_after``, ``blend``, ``residual``) move with
``env.set_progress(fraction of your budget spent)``, which your loop calls; pidlab's trainer
calls it before every rollout.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import gymnasium as gym

from pidlab.checks import instance
from pidlab.controller.spec import CoachSpec, load_spec
from pidlab.errors import CoachingError
from pidlab.experiment.conditions import load_conditions, select
from pidlab.rl.coaching import CoachingWrapper
from pidlab.rl.recipe import parse_coaching
from pidlab.rl.wrap import TRAINER_ONLY, wrapper_arguments


def coach_env(
    env: gym.Env,
    spec: CoachSpec | str | Path,
    condition: str = "rescue-terminal",
    *,
    conditions_file: str | Path | None = None,
    **fields: Any,
) -> CoachingWrapper:
    """``env`` with the coach ``spec`` coupled as ``condition`` couples it in pidlab's experiments.

    Parameters
    ----------
    env : gymnasium.Env
        Your env (a MuJoCo env, usually from ``gymnasium.make``, with its time limit); its id must
        be the spec's.
    spec : CoachSpec or path
        The coach, or its spec file. ``rescue-*`` conditions need its rescue region
        (``pidlab rescue SPEC --write``); ``pidlab`` and ``pidlab-fading`` its bounds box.
    condition : str
        A condition of the conditions file (``coach/conditions.toml``, or ``conditions_file``),
        whose ``coaching`` fields set the wrapper.
    conditions_file : path, optional
    **fields
        Coaching fields (a recipe's ``[coaching]`` names) that replace the condition's.

    Returns
    -------
    CoachingWrapper
        Its accounts (``total_agent_steps``, ``total_coach_steps``, ``total_falls``, ...) count
        every env step; ``set_progress`` moves its schedules.

    Raises
    ------
    CoachingError, ConditionError, SpecError, RecipeError
        One line: an unknown condition, a condition without a coach or with a coupling that needs
        pidlab's trainer, a spec for another env or without the region the condition uses, bad
        coaching fields.
    """
    instance(env, gym.Env, "env", CoachingError)
    if not isinstance(spec, CoachSpec):
        spec = load_spec(spec)
    env_id = env.spec.id if env.spec is not None else None
    if env_id is not None and env_id != spec.env_id:
        raise CoachingError(f"the spec is for {spec.env_id}, the env is {env_id} (expected its spec)")
    source = str(conditions_file or "coach/conditions.toml")
    chosen = select(load_conditions(conditions_file), [condition], source)
    c = chosen[0].for_env(spec.env_id)
    where = f"condition {condition}"
    if c.coach == "none" or c.bounds is not None:
        why = "has no coach" if c.coach == "none" else "gives its own bounds box (coach_env uses the spec's)"
        raise CoachingError(f"{where} {why}; expected a condition that couples a coach, e.g. rescue-terminal")
    coaching = parse_coaching({**c.coaching, **fields}, where)
    needs = [name for name in TRAINER_ONLY if getattr(coaching, name) is not None]
    if needs:
        raise CoachingError(
            f"{where} uses {', '.join(needs)}: pidlab's trainer runs that (pidlab train), not the env; "
            "coach_env couples the coach through the env only: choose a condition without it (e.g. "
            "rescue-terminal, blend, residual)"
        )
    return CoachingWrapper(env, spec, **wrapper_arguments(coaching, True))
