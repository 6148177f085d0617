"""How wrong the model predictor's forecast is, measured where the shield asks it.

:func:`measure_forecast` runs the env behind the exact predictive shield (the spec's rescue region,
the coach taking over at a veto and handing back at half the region) with an agent that acts
uniformly at random: the untrained agent of a training run's start, whose actions are the widest
the forecast must answer for. At every action put to the shield, the exact look-ahead (a copy of
the MuJoCo data) gives the true next observation and :class:`~pidlab.region.forecast.LinearForecast`
its forecast from the same joint state. The first ``transitions`` set the margins (the largest
error per region variable); the next ``held_out`` check them: how many true next observations fall
outside the margins of their forecast (``escapes``), and how often the two predictors agree on a
veto (the model's asked of the margin box about its forecast, :func:`margin_region`: a lookup grid's
or a classifier's rescue region).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np

from pidlab.checks import integer
from pidlab.checks import seed as checked_seed
from pidlab.controller.spec import CoachSpec
from pidlab.errors import CoachingError
from pidlab.lookup import AGREEMENT, ForecastError, region_digest
from pidlab.plant.model import LoadedModel, load_model
from pidlab.region.forecast import (
    ClassifierMarginRegion,
    MarginRegion,
    check_forecastable,
    margin_region,
    margin_variables,
)
from pidlab.region.takeover import Region, observation_indices, region_from_bounds
from pidlab.rl.coaching import CoachingWrapper
from pidlab.rl.predict import Predictor, forecast_of

MAX_TRANSITIONS = 1_000_000
"""The most actions :func:`measure_forecast` records per part (about an hour of Walker2d)."""


def _record(
    spec: CoachSpec, loaded: LoadedModel, count: int, seed: int, tick: Callable[[], None]
) -> tuple[np.ndarray, np.ndarray]:
    """``count`` pairs (true next observation, forecast) from a random agent behind the exact shield."""
    env = CoachingWrapper(gym.make(spec.env_id), spec, mode="takeover", region="rescue", trigger="predictive",
                          handback=0.5, loaded=loaded, seed=seed)  # fmt: skip
    forecast, model = forecast_of(loaded), loaded.model
    truth: list[np.ndarray] = []
    guess: list[np.ndarray] = []

    def listener(data: Any, action: Any, obs: np.ndarray) -> None:
        if len(truth) < count:
            truth.append(np.array(obs, dtype=float))
            guess.append(forecast.observation(model, data.qpos, data.qvel, data.act, action))
            tick()

    lookahead = env.lookahead
    if not isinstance(lookahead, Predictor):
        raise CoachingError(f"{spec.name}: the exact shield has no exact look-ahead")  # never: predictive
    lookahead.listen(listener)
    rng = np.random.default_rng(seed)
    space: Any = env.action_space
    low, high = np.asarray(space.low, dtype=np.float64), np.asarray(space.high, dtype=np.float64)
    env.reset(seed=seed)
    while len(truth) < count:
        _, _, terminated, truncated, _ = env.step(rng.uniform(low, high).astype(space.dtype))
        if terminated or truncated:
            env.reset()
    env.close()
    return np.array(truth), np.array(guess)


def measure_forecast(
    spec: CoachSpec,
    loaded: LoadedModel | None = None,
    transitions: int = 5000,
    held_out: int = 5000,
    seed: int = 0,
    progress: Callable[[int, int], None] | None = None,
) -> ForecastError:
    """The linear forecast's error on the spec's rescue region, and what it does to the shield.

    Parameters
    ----------
    spec : CoachSpec
        A coach with a rescue region derived for the predictive trigger.
    loaded : LoadedModel, optional
        The env's model (default: loaded from the spec's env id).
    transitions, held_out : int
        Actions put to the shield that set the margins, then check them.
    seed : int
        Seeds the env's resets and the random agent.
    progress : callable, optional
        ``progress(done, total)`` after each recorded action.

    Returns
    -------
    ForecastError
        Margins, error quantiles, escapes and veto agreement; ``to_table()`` is ``[bounds.forecast]``.

    Raises
    ------
    CoachingError
        Counts below 1 (``held_out`` below 0) or above :data:`MAX_TRANSITIONS`, no rescue region,
        or a region over a variable no joint-state forecast gives.
    """
    integer(transitions, "transitions", CoachingError, low=1, high=MAX_TRANSITIONS, param="transitions")
    integer(held_out, "held_out", CoachingError, low=0, high=MAX_TRANSITIONS, param="held_out")
    checked_seed(seed, "seed", CoachingError, param="seed")
    loaded = loaded if loaded is not None else load_model(spec.env_id)
    card = loaded.require_card()
    rescue = (spec.bounds or {}).get("rescue")
    if rescue is None:
        raise CoachingError(
            f"{spec.name}: the spec has no rescue region; run `pidlab rescue SPEC --write` first"
        )
    region = region_from_bounds(spec.bounds, card.observation_names, "rescue", spec.name)
    names = margin_variables(region)
    check_forecastable(card, names, f"{spec.name}: pidlab forecast")
    cols = observation_indices(names, card.observation_names, "bounds.rescue")
    total = int(transitions) + int(held_out)
    done = [0]

    def tick() -> None:
        done[0] += 1
        if progress is not None:
            progress(done[0], total)

    truth, guess = _record(spec, loaded, total, int(seed), tick)
    err = np.abs(truth[:, cols] - guess[:, cols])
    fit, check = err[: int(transitions)], err[int(transitions) :]
    margins = fit.max(axis=0)
    escapes = int(np.any(check > margins, axis=1).sum())
    margin = dict(zip(names, margins, strict=True))
    agreement = _agreement(region, margin, card.observation_names, truth[transitions:], guess[transitions:])
    return ForecastError(
        model="linear", variables=names, margins=tuple(float(m) for m in margins),
        median=tuple(float(v) for v in np.median(fit, axis=0)),
        p99=tuple(float(v) for v in np.quantile(fit, 0.99, axis=0)), transitions=int(transitions),
        held_out=int(held_out), escapes=escapes, seed=int(seed), agreement=agreement,
        region=region_digest(rescue),
    )  # fmt: skip


def _agreement(
    region: Region,
    margins: dict[str, float],
    names: tuple[str, ...],
    truth: np.ndarray,
    guess: np.ndarray,
) -> dict[str, int]:
    """Veto by veto: the exact look-ahead's state in the region, the forecast's margin box in it."""
    try:
        shrunk: MarginRegion | ClassifierMarginRegion | None = margin_region(region, margins)
    except CoachingError:  # nothing fits: the model vetoes every action
        shrunk = None
    counts = dict.fromkeys(AGREEMENT, 0)
    for t, g in zip(truth, guess, strict=True):
        exact = not region.contains(t)
        model = shrunk is None or not shrunk.contains(g)
        key = "both" if exact and model else "exact_only" if exact else "model_only" if model else "neither"
        counts[key] += 1
    return counts
