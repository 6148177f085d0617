"""How hard a push the coach alone recovers from: reach per perturbation, falls per 100 episodes.

A rescue region says which states the coach brings back; this says it in a control engineer's
terms. The model card's ``[[perturbation]]`` tables name the pushes (a tilted torso, a shove, a
spin: a direction in joint coordinates or rates). From the operating point, each is applied at
growing magnitudes on both sides, on the floor for a standing robot
(:func:`pidlab.plant.ground.on_floor`), and the coach alone runs for the horizon with its real
discrete law in MuJoCo; a start is recovered when the env's termination rule never fires.

- **Reach**: per perturbation and side, the largest magnitude up to which every probe recovered.
- **Falls per 100 episodes**: episodes from random starts (a perturbation drawn uniformly, its
  magnitude uniformly in ``+-limit``), with a 95 % Clopper-Pearson interval.

A start that puts a joint outside its range is no state the robot can be in (a hip bent past its
stop): it is not probed. On that side the reach stops at the last magnitude whose start lies within
every range (:attr:`Reach.negative_range`, :attr:`Reach.positive_range`), and an episode whose draw
is such a start is drawn again.

Everything is deterministic from ``seed``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import mujoco
import numpy as np
from scipy.stats import binomtest

from pidlab.checks import integer, number
from pidlab.controller.spec import CoachSpec
from pidlab.errors import RegionError
from pidlab.linear.linearize import Linearization, linearize
from pidlab.plant.card import Perturbation
from pidlab.plant.model import LoadedModel
from pidlab.region.simulate import Simulator, horizon_steps

HORIZON_S = 5.0
"""Seconds the coach must hold a perturbed start (the default)."""


@dataclass(frozen=True)
class Reach:
    """How far one perturbation can go on each side before a probe falls.

    Attributes
    ----------
    name, unit : str
    limit : float
        The largest magnitude probed.
    negative, positive : float
        The largest magnitude (>= 0) up to which every probe on that side recovered.
    probes : int
        Magnitudes probed per side (``limit * k / probes``, k = 1..probes).
    negative_range, positive_range : float
        The largest magnitude probed on that side whose start keeps every joint within its range
        (``limit`` where all do): beyond it nothing was probed.
    """

    name: str
    unit: str
    limit: float
    negative: float
    positive: float
    probes: int
    negative_range: float
    positive_range: float

    def past_range(self) -> tuple[str, ...]:
        """The sides whose starts leave a joint's range, and from where (``"+0"``, ``"-0.2"``)."""
        sides = (("-", self.negative_range), ("+", self.positive_range))
        return tuple(f"{sign}{m:.3g}" for sign, m in sides if m < self.limit)


@dataclass(frozen=True)
class Recovery:
    """What one coach recovers from (see the module docstring).

    Attributes
    ----------
    env_id, spec_name : str
    horizon_s : float
    seed : int
    reach : tuple of Reach
        One per perturbation of the model card, in card order.
    episodes, falls : int
        Random-start episodes run and the ones that fell.
    falls_ci : tuple of float
        95 % Clopper-Pearson interval of falls per 100 episodes.
    """

    env_id: str
    spec_name: str
    horizon_s: float
    seed: int
    reach: tuple[Reach, ...]
    episodes: int
    falls: int
    falls_ci: tuple[float, float]

    @property
    def falls_per_100(self) -> float:
        """Falls per 100 random-start episodes (NaN with none run)."""
        return 100.0 * self.falls / self.episodes if self.episodes else float("nan")

    def to_dict(self) -> dict[str, Any]:
        """The figures as plain data (JSON), with the falls per 100 episodes."""
        return {**asdict(self), "falls_per_100": self.falls_per_100}


def perturbations_of(loaded: LoadedModel) -> tuple[Perturbation, ...]:
    """The model card's perturbations.

    Raises
    ------
    RegionError
        The card has none.
    """
    card = loaded.require_card()
    if not card.perturbation:
        raise RegionError(
            f"the model card of {loaded.name} has no [[perturbation]] tables; add one per push to probe "
            "(name, kind = pose|velocity, direction = {joint = weight}, limit)"
        )
    return card.perturbation


def perturbation_start(pt: Perturbation, m: mujoco.MjModel, magnitude: float) -> np.ndarray:
    """The tangent deviation ``(dq, dv)`` from the operating point of ``pt`` at ``magnitude``."""
    x = np.zeros(2 * m.nv)
    base = 0 if pt.kind == "pose" else m.nv
    for joint, weight in pt.direction:
        jid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, joint)
        x[base + int(m.jnt_dofadr[jid])] += weight * magnitude
    return x


def reachable(sim: Simulator, x_plant: np.ndarray) -> bool:
    """Whether the start ``x_plant`` (on the floor) keeps every limited joint within its range."""
    sim.start(x_plant, grounded=True)
    return sim.within_limits()


def survived(sim: Simulator, x_plant: np.ndarray, steps: int) -> int:
    """Control steps the coach alone holds the start ``x_plant`` (on the floor), at most ``steps``."""
    m, d, fast, frame_skip = sim.m, sim.d, sim.fast, sim.loaded.frame_skip
    obs = sim.start(x_plant, grounded=True)
    act = sim.coach.act
    for k in range(steps):
        d.ctrl[:] = act(obs)
        mujoco.mj_step(m, d, nstep=frame_skip)
        obs = fast.observe(d)
        if fast.terminated(d, obs):
            return k
    return steps


def _reach_side(
    sim: Simulator, pt: Perturbation, sign: float, probes: int, steps: int
) -> tuple[float, float]:
    """(reach, the largest magnitude probed within every joint's range) on one side."""
    reach = None
    for k in range(1, probes + 1):
        x = perturbation_start(pt, sim.m, sign * pt.limit * k / probes)
        before = round(pt.limit * (k - 1) / probes, 12)
        if not reachable(sim, x):
            return (before if reach is None else reach), before
        if reach is None and survived(sim, x, steps) < steps:
            reach = before
    return (pt.limit if reach is None else reach), pt.limit


MAX_REDRAWS = 1000
"""Draws per episode before a perturbation table whose starts all leave a joint's range is refused."""


def episode_starts(
    perturbations: Sequence[Perturbation],
    m: mujoco.MjModel,
    episodes: int,
    seed: int,
    scale: float = 1.0,
    keep: Callable[[np.ndarray], bool] | None = None,
) -> list[np.ndarray]:
    """Random starts: a perturbation drawn uniformly, its magnitude uniformly in ``+-scale * limit``.

    ``keep``: a start it refuses is drawn again (:func:`reachable`: within every joint's range).

    Raises
    ------
    RegionError
        :data:`MAX_REDRAWS` draws in a row refused.
    """
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(episodes):
        for _ in range(MAX_REDRAWS):
            pt = perturbations[int(rng.integers(len(perturbations)))]
            x = perturbation_start(pt, m, scale * float(rng.uniform(-pt.limit, pt.limit)))
            if keep is None or keep(x):
                break
        else:
            raise RegionError(f"no perturbed start within the joints' ranges in {MAX_REDRAWS} draws")
        out.append(x)
    return out


def check_settings(
    probes: int, episodes: int, horizon_s: float, seed: int, names: tuple[str, str, str, str] | None = None
) -> None:
    """Refuse a setting out of range (:class:`RegionError` naming it as ``names`` does, if given)."""
    n = names or ("probes", "episodes", "horizon_s", "seed")
    integer(probes, n[0], RegionError, low=1, high=1000)
    integer(episodes, n[1], RegionError, low=0, high=1_000_000)
    number(horizon_s, n[2], RegionError, low=0.0, low_open=True, high=600.0, unit="s")
    integer(seed, n[3], RegionError, low=0)


def measure_recovery(
    spec: CoachSpec,
    loaded: LoadedModel,
    *,
    probes: int = 20,
    episodes: int = 100,
    horizon_s: float = HORIZON_S,
    seed: int = 0,
    lin: Linearization | None = None,
    progress: Callable[[int], None] | None = None,
) -> Recovery:
    """Reach per perturbation and falls per 100 random-start episodes of ``spec``'s coach alone.

    Parameters
    ----------
    spec : CoachSpec
    loaded : LoadedModel
        The model of ``spec.env_id``, whose card holds ``[[perturbation]]`` tables.
    probes : int
        Magnitudes probed per perturbation and side.
    episodes : int
        Random-start episodes.
    horizon_s : float
        Seconds the coach must hold each start.
    seed : int
        Seeds the random starts.
    lin : Linearization, optional
        Supplies the operating point (default: linearized at the card's).
    progress : callable, optional
        Called with the number of simulations run so far.

    Raises
    ------
    RegionError
        No perturbations in the card, or a setting out of range.
    """
    check_settings(probes, episodes, horizon_s, seed)
    perturbations = perturbations_of(loaded)
    sim = Simulator(spec, loaded, lin if lin is not None else linearize(loaded))
    steps = horizon_steps(horizon_s, loaded.control_dt)
    done = 0
    reach = []
    for pt in perturbations:
        (neg, neg_range), (pos, pos_range) = (_reach_side(sim, pt, s, probes, steps) for s in (-1.0, 1.0))
        reach.append(Reach(pt.name, pt.unit, pt.limit, neg, pos, probes, neg_range, pos_range))
        done += 2
        if progress is not None:
            progress(done)
    falls = 0
    for x in episode_starts(perturbations, sim.m, episodes, seed, keep=lambda x: reachable(sim, x)):
        falls += survived(sim, x, steps) < steps
        done += 1
        if progress is not None:
            progress(done)
    ci = binomtest(falls, episodes).proportion_ci(0.95) if episodes else None
    return Recovery(
        env_id=str(loaded.env_id or loaded.name),
        spec_name=spec.name,
        horizon_s=float(horizon_s),
        seed=int(seed),
        reach=tuple(reach),
        episodes=int(episodes),
        falls=int(falls),
        falls_ci=(100.0 * ci.low, 100.0 * ci.high) if ci is not None else (float("nan"), float("nan")),
    )
