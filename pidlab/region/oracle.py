"""The exact rescue test, asked one state at a time, and the least coach share any region allows.

A rescue region (:mod:`pidlab.region.rescue`, :mod:`pidlab.region.classifier`) approximates one
question: from this state, after this action, does the coach alone bring the robot back (into its
certified core, or through the horizon without a termination)? :class:`RescueOracle` answers it
exactly, by simulating the coach's real law in MuJoCo from that very state, the test every label
of a region estimate is made by. It needs a copy of the simulator and a whole rescue's simulation
per question, so no real system can ask it; it is the yardstick the regions are measured against.

:func:`shield_floor` puts it where a shield's region would be. An untrained agent (a Gaussian
policy about zero, clipped to the action range, as SB3's PPO starts) proposes an action at every
step; the action runs when the oracle says the coach rescues the state after it, and otherwise the
coach acts for that one step and hands back at once. No region lets the agent act more often
without letting it into states its coach cannot rescue, and no takeover is shorter: the coach's
share of the env steps under this shield is the floor for that coach and agent, whatever region
or hand-back rule a shield uses.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import gymnasium as gym
import mujoco
import numpy as np

from pidlab.checks import integer, number
from pidlab.checks import seed as check_seed
from pidlab.controller.pid import Coach
from pidlab.controller.spec import CoachSpec
from pidlab.errors import RegionError
from pidlab.plant.model import LoadedModel
from pidlab.region.rescue import _core, _rescued, check_into
from pidlab.region.simulate import Simulator, horizon_steps

HORIZON_S = 3.0
"""The rescue's horizon, s (the region estimates' default)."""


class RescueOracle:
    """Whether ``spec``'s coach alone rescues a state, after an optional action: simulated exactly.

    Parameters
    ----------
    spec : CoachSpec
        A coach with a certified core or a recoverable box (``pidlab bounds``).
    loaded : LoadedModel
        The model of ``spec.env_id``, with a model card.
    horizon_s : float
        The rescue's horizon, s.
    into : {"core", "box"}
        Where a rescue ends (:data:`pidlab.region.rescue.RESCUE_ENDS`): the region estimates'
        criterion, or survive the horizon and end it in the recoverable box.

    Raises
    ------
    RegionError
        A setting out of range, or a spec with nothing to rescue into.
    """

    def __init__(
        self, spec: CoachSpec, loaded: LoadedModel, horizon_s: float = HORIZON_S, into: str = "core"
    ) -> None:
        from pidlab.controller.analysis import analyze_coach

        number(horizon_s, "horizon_s", RegionError, low=0.0, low_open=True, high=600.0, unit="s")
        check_into(into)
        self.lin = analyze_coach(Coach(spec, loaded), loaded).linearization
        self.sim = Simulator(spec, loaded, self.lin)
        self.core = _core(spec, loaded.require_card(), into)
        self.steps = horizon_steps(horizon_s, loaded.control_dt)
        self.questions = 0

    def rescues(self, x_plant: np.ndarray, ctrl: np.ndarray | None = None) -> bool:
        """From the tangent deviation ``x_plant`` (:meth:`Simulator.plant_state`), after one step of ``ctrl``.

        ``ctrl=None``: the coach acts from the state itself (a predictive trigger's question about
        the state an action led to, or a start).
        """
        x = _finite_vector(x_plant, 2 * self.sim.m.nv, "x_plant")
        kick = None if ctrl is None else _finite_vector(ctrl, self.sim.m.nu, "ctrl") - self.lin.op.ctrl
        self.questions += 1
        return _rescued(self.sim, (x, kick), self.steps, self.core)[0]


def _finite_vector(value: object, size: int, name: str) -> np.ndarray:
    """``value`` as a float vector of ``size`` finite numbers, else a one-line :class:`RegionError`."""
    expected = f"{name}: expected {size} finite number{'' if size == 1 else 's'}"
    try:
        v = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise RegionError(f"{expected}, got {type(value).__name__}") from None
    if v.shape != (size,):
        raise RegionError(f"{expected}, got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise RegionError(f"{expected}, got a non-finite value")
    return v


@dataclass(frozen=True)
class FloorEpisode:
    """One episode under the oracle shield.

    Attributes
    ----------
    steps : int
        Env steps, up to the env's time limit or its termination.
    coach_steps : int
        Of them, the steps where the coach acted (the agent's action would have left what it rescues).
    fell : bool
        The episode ended in a termination (only a step of the coach can lead there).
    start_rescued : bool
        The coach rescues the reset state itself.
    """

    steps: int
    coach_steps: int
    fell: bool
    start_rescued: bool


@dataclass(frozen=True)
class ShieldFloor:
    """The least coach share for one coach and an untrained agent: :func:`shield_floor`'s result."""

    env_id: str
    coach: str
    into: str
    horizon_s: float
    std: float
    seed: int
    episodes: tuple[FloorEpisode, ...]

    @property
    def steps(self) -> int:
        """Env steps over every episode."""
        return sum(e.steps for e in self.episodes)

    @property
    def coach_steps(self) -> int:
        """Coach steps over every episode."""
        return sum(e.coach_steps for e in self.episodes)

    @property
    def coach_share(self) -> float:
        """The coach's share of the env steps, all episodes pooled."""
        return self.coach_steps / self.steps if self.steps else float("nan")

    @property
    def falls(self) -> int:
        """Episodes that ended in a termination."""
        return sum(e.fell for e in self.episodes)


Start = tuple[np.ndarray, np.ndarray]
"""A reset state: ``(qpos, qvel)``."""


def reset_states(env_id: str, episodes: int, seed: int) -> tuple[list[Start], int, gym.spaces.Box]:
    """The env's own reset states for seeds ``seed, seed+1, ...``, its time limit and action space.

    Raises
    ------
    RegionError
        ``env_id`` is no Gymnasium env (register your own with ``--gym-packages``).
    """
    try:
        env = gym.make(env_id)
    except gym.error.Error as exc:
        why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise RegionError(f"{env_id}: no Gymnasium env to draw reset states from ({why})") from None
    try:
        states = []
        for k in range(episodes):
            env.reset(seed=seed + k)
            data = env.unwrapped.data  # type: ignore[attr-defined]
            states.append((data.qpos.copy(), data.qvel.copy()))
        limit = env.spec.max_episode_steps if env.spec and env.spec.max_episode_steps else 1000
        return states, int(limit), env.action_space  # type: ignore[return-value]
    finally:
        env.close()


def untrained_agent(space: gym.spaces.Box, std: float, rng: np.random.Generator) -> Callable[[], np.ndarray]:
    """An untrained agent's actions: ``N(0, std^2)`` each, clipped to ``space`` (SB3's PPO at start)."""
    low, high = space.low.astype(float), space.high.astype(float)

    def draw() -> np.ndarray:
        return np.clip(rng.normal(0.0, std, size=low.shape), low, high)

    return draw


def shield_episode(
    oracle: RescueOracle, run: Simulator, start: Start, limit: int,
    draw: Callable[[], np.ndarray], seen: Callable[[np.ndarray, np.ndarray, bool], None] | None = None,
) -> FloorEpisode:  # fmt: skip
    """One episode from ``start`` (qpos, qvel): the agent's draws, vetted by ``oracle``.

    ``run`` steps the episode (a :class:`Simulator` of its own, not ``oracle.sim``). ``seen``, if
    given, is told each question: the tangent state, the agent's action and whether it ran.
    """
    m, d, frame_skip = run.m, run.d, run.loaded.frame_skip
    mujoco.mj_resetData(m, d)
    d.qpos[:], d.qvel[:] = start
    mujoco.mj_forward(m, d)
    obs = run.observe()
    start_rescued = oracle.rescues(run.plant_state())
    coach_steps = 0
    for step in range(1, limit + 1):
        action, x = draw(), run.plant_state()
        allowed = oracle.rescues(x, action)
        if seen is not None:
            seen(x, action, allowed)
        if allowed:
            d.ctrl[:] = action
        else:
            coach_steps += 1
            run.coach.reset(obs)
            d.ctrl[:] = run.coach.act(obs)
        mujoco.mj_step(m, d, nstep=frame_skip)
        obs = run.observe()
        if run.terminated(obs):
            return FloorEpisode(step, coach_steps, True, start_rescued)
    return FloorEpisode(limit, coach_steps, False, start_rescued)


def shield_floor(
    spec: CoachSpec,
    loaded: LoadedModel,
    *,
    episodes: int = 10,
    std: float = 1.0,
    seed: int = 0,
    horizon_s: float = HORIZON_S,
    into: str = "core",
    max_steps: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> ShieldFloor:
    """The coach's share of the env steps when an untrained agent is shielded by the exact rescue test.

    Parameters
    ----------
    spec, loaded, horizon_s, into
        As for :class:`RescueOracle`.
    episodes : int
        Episodes, from the env's reset states for seeds ``seed`` to ``seed + episodes - 1``.
    std : float
        The agent's action noise: each action is ``N(0, std^2)`` per component, clipped to the
        action range (SB3's PPO starts at ``std = 1`` with a mean near 0).
    seed : int
        The reset states' and the actions' seed: the same seed, the same result.
    max_steps : int, optional
        Steps per episode at most (default: the env's time limit).
    progress : callable, optional
        Called with the number of episodes done.

    Returns
    -------
    ShieldFloor

    Raises
    ------
    RegionError
        A setting out of range.
    """
    integer(episodes, "episodes", RegionError, low=1, high=100_000)
    number(std, "std", RegionError, low=0.0, low_open=True, high=100.0)
    check_seed(seed, "seed", RegionError)
    if max_steps is not None:
        integer(max_steps, "max_steps", RegionError, low=1, high=10**7)
    starts, limit, space = reset_states(spec.env_id, episodes, seed)
    oracle = RescueOracle(spec, loaded, horizon_s, into)
    run = Simulator(spec, loaded, oracle.lin)
    limit = limit if max_steps is None else int(max_steps)
    draw = untrained_agent(space, std, np.random.default_rng(seed))
    done = []
    for start in starts:
        done.append(shield_episode(oracle, run, start, limit, draw))
        if progress is not None:
            progress(len(done))
    return ShieldFloor(spec.env_id, spec.name, into, float(horizon_s), float(std), int(seed), tuple(done))
