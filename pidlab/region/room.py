"""Tuning for room: the coach whose rescue region is largest under the actuator limits.

The ``robust`` preset shapes crossover and phase margin; on the cart-pole it leaves the cart
loop nearly off (kp about 0.004), so a rescue that starts with the cart moving ends on the rail.
The ``room`` preset instead picks, among discrete LQR designs projected on the coach's PD
structure (:func:`pidlab.controller.autotune.lqr_projection`) with input weights
:data:`INPUT_WEIGHTS`, the one that rescues the most states of the model card's rescue domain
(:func:`pidlab.region.rescue.rescued_fraction`: real MuJoCo, the coach's saturation, the env's
termination; rescued means brought into the candidate's own certified core, from
:func:`pidlab.region.roa.estimate_roa`). Every candidate is scored on the same states. The
margins of the chosen coach are reported as for the other presets.

On the contact-rich envs (Hopper, Walker2d), whose robust coach is refined on the env, the linear
designs hold little; there the preset searches the gains on the env for the coach that holds the
most of the model card's perturbed starts (:mod:`pidlab.region.room_env`). An env with neither a
state-measuring linear design nor ``[[perturbation]]`` tables is refused.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from pidlab.controller.autotune import PRESETS, TuneResult, lqr_projection, tune_result, tuning_problem
from pidlab.controller.spec import CoachSpec
from pidlab.errors import PidlabError, RegionError
from pidlab.linear.linearize import Linearization, linearize
from pidlab.plant.card import ModelCard
from pidlab.plant.model import LoadedModel
from pidlab.region.rescue import default_settings, rescued_fraction

INPUT_WEIGHTS = (0.1, 0.5, 2.0, 10.0, 50.0, 250.0)
"""LQR input weights tried (larger: gentler gains, less saturation)."""

ROOM_SAMPLES = 300
"""States of the rescue domain every candidate is scored on."""


CORE_SAMPLES = 300
"""Simulated states certifying each candidate's core (the full ``pidlab roa`` uses 1000)."""


def _with_core(spec: CoachSpec, loaded: LoadedModel, seed: int, workers: int | None) -> CoachSpec:
    """``spec`` with its certified Lyapunov core as ``[bounds.ellipsoid]`` (unchanged without one)."""
    from pidlab.region.roa import estimate_roa

    try:
        roa, _ = estimate_roa(spec, loaded, samples=CORE_SAMPLES, seed=seed, workers=workers)
    except RegionError:
        return spec
    lyap = roa.lyapunov
    if lyap is None:
        return spec
    ellipsoid = {
        "variables": list(lyap.variables),
        "center": [float(v) for v in lyap.center],
        "shape": [[float(v) for v in row] for row in lyap.P_y],
        "level": float(roa.level),
        "rho": 1.0,
    }
    return replace(spec, bounds={"method": roa.method, "ellipsoid": ellipsoid})


def has_room_design(card: ModelCard) -> bool:
    """Whether the room preset can tune the env of ``card``.

    It needs a tuning template, and either a linear design that measures the state (the coach is
    not refined on the env) or perturbed starts to search the gains on (``[[perturbation]]``).
    """
    return bool(card.tuning) and (not card.refine_on_env or bool(card.perturbation))


def tune_for_room(
    loaded: LoadedModel,
    lin: Linearization | None = None,
    samples: int = ROOM_SAMPLES,
    seed: int = 0,
    workers: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> TuneResult:
    """The ``room`` preset (see the module docstring).

    Parameters
    ----------
    loaded : LoadedModel
        An env with a model card: template and ``[rescue]`` domain (pendulums), or template and
        ``[[perturbation]]`` tables (envs whose coach is refined on the env).
    lin : Linearization, optional
        Default: at the card's operating point.
    samples : int
        States each candidate is scored on (pendulums; the search on the env scores each on
        :data:`pidlab.region.room_env.ROOM_EPISODES` perturbed starts).
    seed : int
    workers : int, optional
        Worker processes for the simulations (pendulums; the search on the env runs in this
        process).
    progress : callable, optional
        Called with the number of candidates scored so far.

    Raises
    ------
    PidlabError
        The env's coach is refined on the env (contacts), or no candidate rescues anything.
    """
    card = loaded.require_card()
    if not has_room_design(card):
        raise PidlabError(
            f"preset room: {loaded.name} has no linear design that measures its state (its coach is "
            "refined on the env) and no [[perturbation]] tables to search its gains on; use the robust preset"
        )
    lin = lin if lin is not None else linearize(loaded)
    if card.refine_on_env:
        from pidlab.region.room_env import tune_room_on_env

        return tune_room_on_env(loaded, lin, seed=seed, progress=progress)
    problem, _ = tuning_problem(loaded, card, lin, PRESETS["robust"])
    scores = []
    for i, w in enumerate(INPUT_WEIGHTS):
        gains, _ = lqr_projection(lin, problem.loops, input_weight=w)
        spec = _with_core(problem.spec(gains, "pidlab-room"), loaded, seed, workers)
        settings = replace(default_settings(spec, loaded), seed=seed)
        score = rescued_fraction(spec, loaded, settings, samples, workers) if spec.bounds else 0.0
        scores.append((score, w, gains))
        if progress is not None:
            progress(i + 1)
    best = max(scores, key=lambda t: (t[0], t[1]))
    if best[0] <= 0.0:
        raise PidlabError(f"preset room: no candidate coach rescues any state of {loaded.name}'s domain")
    text = (
        f"pidlab auto-tuned coach (room preset) for {loaded.env_id}: the discrete LQR design, projected on "
        f"the PD structure, whose rescue region is largest (input weight {best[1]} of {list(INPUT_WEIGHTS)}; "
        f"{best[0]:.0%} of {samples} states of the rescue domain rescued)."
    )
    extra = {
        "room_input_weight": best[1],
        "room_rescued_fraction": best[0],
        "room_candidates": {str(w): float(f) for f, w, _ in scores},
        "room_samples": samples,
    }
    spec = problem.spec(np.asarray(best[2]), "pidlab-room")
    nan = float("nan")
    return tune_result(spec, loaded, lin, "room", (nan, nan), len(scores), None, text, extra)
