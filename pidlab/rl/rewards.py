"""What an env pays: its reward on a failing step, and its reward per surviving step.

The coaching wrapper's ``terminal`` view pays the agent's transition what the env would have paid
had that step failed (:func:`failure_reward`); its ``penalty`` view prices a takeover in steps of
the env's alive reward (:func:`alive_reward`). Both are facts of the env, kept as data in its model
card's ``[reward]`` table (:class:`pidlab.plant.card.RewardFacts`), so that every view works on any
env with a card; the shipped cards hold them as Gymnasium's v5 sources compute them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import gymnasium as gym

from pidlab.errors import CoachingError, ModelCardError, UnknownEnvError

FailureReward = Callable[[float, dict[str, Any]], float]
"""``(reward, info) -> what the step would have paid had it failed``."""


def failure_function(env_id: str) -> FailureReward:
    """The failure reward of ``env_id``, from its model card's ``[reward] failure`` terms.

    The function sums the step's info terms in the card's order, from 0.0: the same terms and
    operations as Gymnasium's v5 sources on a failing step, so the result is bit for bit the
    env's (InvertedPendulum ``[]``: 0; InvertedDoublePendulum ``distance_penalty`` and
    ``velocity_penalty``; Hopper and Walker2d ``reward_forward`` and ``reward_ctrl``).

    Raises
    ------
    CoachingError
        An env without a card, or whose card gives no ``[reward] failure``: one line saying where
        to add it.
    """
    terms = _card_facts(env_id, "failure", "view = 'terminal'").failure
    return FailureTerms(env_id, tuple(terms))


@dataclass(frozen=True)
class FailureTerms:
    """A failure reward: the sum of the step-info ``terms``, in order, from 0.0 (picklable)."""

    env_id: str
    terms: tuple[str, ...]

    def __call__(self, reward: float, info: dict[str, Any]) -> float:
        """What the step (its ``reward`` and ``info``) would have paid had it failed.

        Raises
        ------
        CoachingError
            The info lacks a term, or it is no number.
        """
        total = 0.0
        for name in self.terms:
            try:
                total = total + float(info[name])
            except (KeyError, TypeError, ValueError):
                raise CoachingError(
                    f"{self.env_id}: the step's info has no number {name!r} (its card's [reward] failure "
                    f"names it); info has: {', '.join(sorted(map(str, info))) or 'nothing'}"
                ) from None
        return total


def failure_reward(env_id: str, reward: float, info: dict[str, Any]) -> float:
    """What the env would have paid for a step had that step failed (terminated).

    See :func:`failure_function`; a wrapper that pays many steps keeps the function instead.

    Parameters
    ----------
    env_id : str
        An env whose model card gives ``[reward] failure``.
    reward : float
        The step's reward.
    info : dict
        The step's info (its reward terms).

    Raises
    ------
    CoachingError
        An env whose failure reward its card does not give.
    """
    return failure_function(env_id)(reward, info)


def alive_reward(env: gym.Env) -> float:
    """The env's reward per surviving step: its card's ``[reward] alive``, else the env's ``healthy_reward``.

    Raises
    ------
    CoachingError
        An env whose card gives none and that has no ``healthy_reward`` (set ``cost`` explicitly,
        or add it to the card).
    """
    env_id = env.spec.id if env.spec is not None else None
    facts = _card_facts(env_id, None, "") if env_id is not None else None
    if facts is not None and facts.alive is not None:
        return float(facts.alive)
    value = getattr(env.unwrapped, "_healthy_reward", None)
    if value is None:
        name = env_id or type(env.unwrapped).__name__
        raise CoachingError(
            f"{name} has no alive reward to price a takeover in: set the recipe's cost, or add "
            f"[reward] alive = ... to its model card"
        )
    return float(value)


def _card_facts(env_id: str, needed: str | None, who: str) -> Any:
    """The card's :class:`~pidlab.plant.card.RewardFacts` (None: no card); ``needed`` must be given.

    Raises
    ------
    CoachingError
        ``needed`` is not given (or the card is missing or damaged), naming the card's file.
    """
    from pidlab.plant.model import load_model

    try:
        card = load_model(env_id).card  # models/' card, else the env's own (a CardEnv's)
    except (ModelCardError, UnknownEnvError) as exc:
        if needed is None:
            return None
        raise CoachingError(f"{who} needs the {needed} reward of {env_id}: {exc}") from None
    facts = card.reward if card is not None else None
    if needed is not None and (facts is None or getattr(facts, needed) is None):
        where = f"its model card {card.path}" if card is not None else f"a model card models/{env_id}.toml"
        example = '["reward_forward", "reward_ctrl"]' if needed == "failure" else "1.0"
        raise CoachingError(
            f"{who} needs the {needed} reward of {env_id}: add [reward] {needed} = ... to {where} "
            f"(e.g. {needed} = {example}; docs/linearization.md, Model cards)"
        )
    return facts
