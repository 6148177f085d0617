"""Model cards: per env, the operating point, the observation map and the termination limits.

A model card is a TOML file in ``models/`` named after the env id (``models/Hopper-v5.toml``).
It is data a user reads and edits; this module parses and validates it. The observation map
names every entry of the Gymnasium observation by the MuJoCo quantity it is computed from,
so that later stages (coach, regions of attraction, bounds) address signals by name.

Schema ``pidlab.model-card/1``::

    schema = "pidlab.model-card/1"
    env_id = "InvertedPendulum-v5"
    description = "..."

    [operating_point]          # where the coach holds the system
    name = "upright"
    qpos = [0.0, 0.0]
    qvel = [0.0, 0.0]
    ctrl = [0.0]
    note = "how it was chosen"

    [[observation]]            # one table per observation entry, in observation order
    name = "hinge_pos"         # unique; used by every later stage
    source = "qpos"            # qpos | qvel | qfrc_constraint
    joint = "hinge"            # joint whose coordinate is read
    transform = "identity"     # identity | sin | cos
    clip = [-10.0, 10.0]       # optional
    unit = "rad"
    description = "pole angle from upright"

    [[termination]]            # the env terminates when any signal leaves its healthy range
    signal = "hinge_pos"       # <joint>_pos, <joint>_vel, or site:<site>:x|y|z
    low = -0.2
    high = 0.2
    interval = "closed"        # closed: healthy iff low <= v <= high; open: low < v < high

    [tuning]                   # optional: how pidlab.controller.autotune structures a coach
    refine_on_env = false      # true: refine the gains on the real env after the linear design
                               # (soft contacts make the linear model kinked at the point)
    [[tuning.loop]]            # one per loop, in order
    name = "pole"
    signal = "hinge_pos"       # the measured observation variable
    rate_signal = "hinge_vel"  # optional: its rate, for the derivative term
    actuators = { slide = 1.0 }  # actuator -> weight; {} = read off the LQR start
    core = true                # false: dropped by presets that keep the core loops only

    [region]                   # optional: how pidlab.region derives the takeover region
    method = "lyapunov"        # lyapunov (certified level set) | simulation (recoverable box)
    variables = ["rooty_pos", "rooty_vel"]  # simulation only: the box's position and its rate

    [rescue]                   # optional: what pidlab.region.rescue's estimate covers
    variables = ["hinge_pos", "hinge_vel"]  # the lookup grid's variables (a joint's position,
                                            # its sine or its velocity)
    half_range = [0.2, 2.0]    # the grid's half-widths about the operating point
    cells = [40, 40]           # cells per grid variable
    guard = { slider_pos = 0.3 }  # other variables drawn within +-these (and required there)

    [[perturbation]]           # optional: the pushes `pidlab recovery` probes the coach with
    name = "tilt"              # unique
    kind = "pose"              # pose (joint coordinates) | velocity (joint rates)
    direction = { hinge = 1.0 }  # joint -> change per unit of the perturbation
    limit = 0.5                # probed within +-limit units
    unit = "rad"
    description = "pole tilted from upright"

    [balance]                  # optional, a robot that stands on its feet: the balance preset's posture
    feet = ["foot_geom"]       # the geoms it stands on
    bend = { leg_joint = -0.15 }  # joints held at these angles (knees off their range limits)
    hips = ["thigh_joint"]     # joints that take the solved hip angle
    ankles = ["foot_joint"]    # joints that take the solved ankle angle (feet flat)
    height = "rootz"           # the base's vertical slide and pitch hinge, free while it settles
    pitch = "rooty"

    [reward]                   # optional: what the env pays, for the coaching views
    alive = 1.0                # its reward per surviving step (the penalty view prices a takeover in it)
    failure = []               # the info terms whose sum is its reward on a failing step ([] = 0);
                               # e.g. ["reward_forward", "reward_ctrl"] on Hopper-v5

    [model]                    # optional: the MJCF the card describes (a robot with no env yet)
    mjcf = "../cartpole.xml"   # relative to the card's folder (or absolute)
    frame_skip = 2             # MuJoCo steps per control period (default 1)
    max_episode_steps = 1000   # an episode's time limit, in control periods (default 1000)

    [paper]                    # optional: what the paper published for this env
    win_target = 800           # the score a "win" needs
    episodes_to_5_wins = { coached = 100, uncoached = 160 }     # Table II
    episodes_to_average = { coached = 104, uncoached = 159 }    # Table II
    savings_percent = { wins = 37.5, average = 34.6 }         # as printed
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mujoco

from pidlab.checks import (
    as_table,
    check_name,
    clip,
    flag,
    integer,
    is_name,
    number,
    path_under,
    shown,
    text,
)
from pidlab.data import data_files, find_data_file, models_dir
from pidlab.errors import ModelCardError
from pidlab.files import read_file, read_toml

MJCF_SUFFIXES = (".xml", ".mjcf", ".mjb")
"""The suffixes of model files: MJCF (``.xml``, ``.mjcf``) and MuJoCo's binary models (``.mjb``)."""

CARD_SCHEMA = "pidlab.model-card/1"
OBS_SOURCES = ("qpos", "qvel", "qfrc_constraint")
OBS_TRANSFORMS = ("identity", "sin", "cos")
INTERVALS = ("closed", "open")
REGION_METHODS = ("lyapunov", "simulation")


@dataclass(frozen=True)
class ObservationVariable:
    """One entry of a Gymnasium observation, named by the MuJoCo quantity it reads.

    Attributes
    ----------
    name : str
        Unique name used by every later stage, e.g. ``"hinge_vel"``.
    source : {"qpos", "qvel", "qfrc_constraint"}
        The ``MjData`` array read.
    joint : str
        The (hinge or slide) joint whose coordinate is read.
    transform : {"identity", "sin", "cos"}
        Function applied to the coordinate.
    clip : tuple of float or None
        ``(low, high)`` clipping applied by the env, if any.
    unit : str
        Physical unit, for tables.
    description : str
        What it is, in words.
    """

    name: str
    source: str
    joint: str
    transform: str = "identity"
    clip: tuple[float, float] | None = None
    unit: str = ""
    description: str = ""


@dataclass(frozen=True)
class Signal:
    """A state signal named on a model card, parsed: a joint's position or rate, or a site's coordinate.

    Attributes
    ----------
    kind : {"pos", "vel", "site"}
    name : str
        The joint's name (``pos``, ``vel``) or the site's (``site``).
    axis : int
        The site's coordinate (0: x, 1: y, 2: z); 0 for a joint.
    """

    kind: str
    name: str
    axis: int = 0


def parse_signal(signal: str) -> Signal | None:
    """``<joint>_pos``, ``<joint>_vel`` or ``site:<site>:x|y|z`` parsed (None for other text).

    The one reading of the signal syntax: the card's checks, the observation's and the termination
    rule's lookups and the forecast's limits all use it. Whether the joint or site exists in a model
    is the caller's check.
    """
    if signal.startswith("site:"):
        site, _, axis = signal[5:].rpartition(":")
        return Signal("site", site, "xyz".index(axis)) if site and axis in ("x", "y", "z") else None
    joint, _, kind = signal.rpartition("_")
    return Signal(kind, joint) if joint and kind in ("pos", "vel") else None


@dataclass(frozen=True)
class TerminationLimit:
    """A healthy range of one signal; the env terminates when the signal leaves it.

    Attributes
    ----------
    signal : str
        ``<joint>_pos``, ``<joint>_vel`` or ``site:<site>:x|y|z``.
    low, high : float
        Healthy range (``-inf``/``inf`` for one-sided limits).
    interval : {"closed", "open"}
        Whether the bounds themselves are healthy.
    description : str
    """

    signal: str
    low: float
    high: float
    interval: str = "closed"
    description: str = ""

    def healthy(self, value: float) -> bool:
        """Whether ``value`` lies in the healthy range."""
        if self.interval == "closed":
            return self.low <= value <= self.high
        return self.low < value < self.high


@dataclass(frozen=True)
class CardOperatingPoint:
    """The operating point recorded in a model card."""

    name: str
    qpos: tuple[float, ...]
    qvel: tuple[float, ...]
    ctrl: tuple[float, ...]
    note: str = ""


@dataclass(frozen=True)
class TuningLoop:
    """One loop of an env's tuning template: what it measures and drives; the tuner finds the gains.

    Attributes
    ----------
    name : str
    signal : str
        The measured observation variable.
    rate_signal : str or None
        Its rate, for the derivative term.
    actuators : tuple of (str, float)
        Actuator names and weights; empty: the weights are read off the LQR start.
    core : bool
        Kept by presets that keep the core loops only.
    """

    name: str
    signal: str
    rate_signal: str | None
    actuators: tuple[tuple[str, float], ...]
    core: bool = True

    @property
    def auto_weights(self) -> bool:
        """No fixed actuators: the weights are read off the LQR start (e.g. torso pitch)."""
        return not self.actuators


@dataclass(frozen=True)
class PaperNumbers:
    """What the paper published for one env (Table II and the printed savings).

    Attributes
    ----------
    win_target : float
        The training score that counts as a win.
    wins_coached, wins_uncoached : int
        Episodes to 5 consecutive wins, with and without PID coaching.
    average_coached, average_uncoached : int
        Episodes until the moving average reached the target, with and without.
    savings_wins, savings_average : float
        The savings in percent as the paper prints them (not recomputed).
    """

    win_target: float
    wins_coached: int
    wins_uncoached: int
    average_coached: int
    average_uncoached: int
    savings_wins: float
    savings_average: float


@dataclass(frozen=True)
class RescueDomain:
    """What a rescue-region estimate covers (the card's ``[rescue]`` table).

    Attributes
    ----------
    variables : tuple of str
        The lookup grid's variables.
    half_range : tuple of float
        Its half-widths about the operating point.
    cells : tuple of int
        Cells per grid variable.
    guard : tuple of (str, float)
        Other variables and their half-widths about the operating point.
    """

    variables: tuple[str, ...]
    half_range: tuple[float, ...]
    cells: tuple[int, ...]
    guard: tuple[tuple[str, float], ...] = ()


PERTURBATION_KINDS = ("pose", "velocity")


@dataclass(frozen=True)
class Perturbation:
    """A perturbed start the recovery measurement probes (one ``[[perturbation]]`` table).

    Attributes
    ----------
    name : str
    kind : {"pose", "velocity"}
        ``pose``: the joints' coordinates move (rad or m per unit); ``velocity``: their rates.
    direction : tuple of (str, float)
        Joint -> change per unit of the perturbation.
    limit : float
        The perturbation is probed within ``+-limit`` units.
    unit : str
    description : str
    """

    name: str
    kind: str
    direction: tuple[tuple[str, float], ...]
    limit: float
    unit: str = ""
    description: str = ""


@dataclass(frozen=True)
class Balance:
    """How a robot that stands on its feet is posed for the ``balance`` preset (the ``[balance]`` table).

    The posture keeps the ``bend`` joints at their angles (knees off their range limits), the torso
    at its operating-point pitch, and solves one hip angle (every ``hips`` joint) and one ankle
    angle (every ``ankles`` joint) so that the feet lie flat and the centre of mass is over the
    middle of the feet (:mod:`pidlab.controller.balance`).

    Attributes
    ----------
    feet : tuple of str
        The geoms the robot stands on (capsules or boxes, lying along the walking direction).
    bend : tuple of (str, float)
        Joint -> fixed angle (rad).
    hips, ankles : tuple of str
        Joints that take the solved hip angle and the solved ankle angle.
    height, pitch : str
        The base's vertical slide and pitch hinge, free while the posture settles on the floor.
    description : str
    """

    feet: tuple[str, ...]
    bend: tuple[tuple[str, float], ...]
    hips: tuple[str, ...]
    ankles: tuple[str, ...]
    height: str
    pitch: str
    description: str = ""

    def joints(self) -> tuple[str, ...]:
        """Every joint the table names."""
        return (*(j for j, _ in self.bend), *self.hips, *self.ankles, self.height, self.pitch)

    def check_against(self, model: mujoco.MjModel, where: str) -> None:
        """Every joint and geom named exists in ``model``, and every bend lies in its joint's range.

        Raises
        ------
        ModelCardError
        """
        for joint in self.joints():
            _joint_id(model, joint, where)
        for joint, angle in self.bend:
            jid = _joint_id(model, joint, where)
            lo, hi = model.jnt_range[jid]
            if model.jnt_limited[jid] and not lo <= angle <= hi:
                raise ModelCardError(f"{where}.bend.{joint} = {angle:g}: outside the joint's range "
                                     f"[{lo:.4g}, {hi:.4g}]")  # fmt: skip
        for geom in self.feet:
            if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, geom) < 0:
                raise ModelCardError(f"{where}.feet: no geom {clip(geom, 40)!r} in the model")


@dataclass(frozen=True)
class CardModel:
    """The MJCF file a card describes, with how an env of it would step (the ``[model]`` table).

    Attributes
    ----------
    mjcf : str
        The MJCF file's absolute path (the card gives it relative to its own folder).
    frame_skip : int
        MuJoCo steps per control period.
    max_episode_steps : int
        An episode's time limit, in control periods.
    """

    mjcf: str
    frame_skip: int = 1
    max_episode_steps: int = 1000


@dataclass(frozen=True)
class RewardFacts:
    """What an env pays, as the coaching views need it.

    Attributes
    ----------
    alive : float or None
        Its reward per surviving step (None: not given).
    failure : tuple of str or None
        The step-info terms whose sum is its reward on a failing (terminated) step, added in this
        order from 0.0; empty: 0 (None: not given).
    """

    alive: float | None = None
    failure: tuple[str, ...] | None = None


@dataclass(frozen=True)
class ModelCard:
    """A parsed model card (see the module docstring for the schema).

    Attributes
    ----------
    env_id : str
    description : str
    operating_point : CardOperatingPoint
    observation : tuple of ObservationVariable
        In observation order.
    termination : tuple of TerminationLimit
    terminate_on_nonfinite : bool
        The env also terminates when the observation has a NaN or inf.
    path : str
        The file the card was read from.
    tuning : tuple of TuningLoop
        The auto-tuner's template (empty: the env has none).
    refine_on_env : bool
        The auto-tuner refines the gains on the real env (contact-rich envs).
    region_method : {"lyapunov", "simulation"}
        How the takeover region is derived.
    region_variables : tuple of str
        The simulation method's box variables: a joint position and its rate.
    paper : PaperNumbers or None
        What the paper published for this env.
    rescue : RescueDomain or None
        What a rescue-region estimate covers by default.
    reward : RewardFacts
        What the env pays (its alive and failure rewards), for the coaching views.
    model : CardModel or None
        The MJCF file it describes (its ``[model]`` table), so that the control stages run on a
        robot with no Gymnasium env; None: the env's own model.
    perturbation : tuple of Perturbation
        The perturbed starts ``pidlab recovery`` probes a coach with (empty: none).
    balance : Balance or None
        How the ``balance`` preset poses a robot that stands on its feet (None: no such preset).
    """

    env_id: str
    description: str
    operating_point: CardOperatingPoint
    observation: tuple[ObservationVariable, ...]
    termination: tuple[TerminationLimit, ...]
    terminate_on_nonfinite: bool
    path: str
    tuning: tuple[TuningLoop, ...] = ()
    refine_on_env: bool = False
    region_method: str = "lyapunov"
    region_variables: tuple[str, ...] = ()
    paper: PaperNumbers | None = None
    rescue: RescueDomain | None = None
    reward: RewardFacts = RewardFacts()
    model: CardModel | None = None
    perturbation: tuple[Perturbation, ...] = ()
    balance: Balance | None = None

    @property
    def observation_names(self) -> tuple[str, ...]:
        """Names of the observation entries, in observation order."""
        return tuple(v.name for v in self.observation)

    def variable(self, name: str) -> ObservationVariable:
        """The observation variable called ``name``.

        Raises
        ------
        UnknownSignalError
            With the list of valid names.
        """
        from pidlab.errors import UnknownSignalError

        for v in self.observation:
            if v.name == name:
                return v
        raise UnknownSignalError(
            f"{name!r} is not an observation variable of {self.env_id}; "
            f"valid names: {', '.join(self.observation_names)}"
        )

    def check_against(self, model: mujoco.MjModel, frame_skip: int) -> None:
        """Check that every joint, site and actuator the card names exists in ``model``.

        Raises
        ------
        ModelCardError
        """
        for v in self.observation:
            _joint_id(model, v.joint, f"{self.path}: observation {v.name!r}")
        for t in self.termination:
            _check_signal(model, t.signal, f"{self.path}: termination signal {t.signal!r}")
        from pidlab.plant.model import actuator_names  # the names every stage uses

        inputs = actuator_names(model)
        for lp in self.tuning:
            for actuator, _ in lp.actuators:
                if actuator not in inputs:
                    raise ModelCardError(
                        f"{self.path}: tuning.loop {lp.name!r}: no actuator {clip(actuator, 40)!r} in the "
                        f"model; actuators: {', '.join(inputs)}"
                    )
        for pt in self.perturbation:
            for joint, _ in pt.direction:
                _joint_id(model, joint, f"{self.path}: perturbation {pt.name!r}")
        if self.balance is not None:
            self.balance.check_against(model, f"{self.path}: balance")
        op = self.operating_point
        for field, values, n in (
            ("qpos", op.qpos, model.nq),
            ("qvel", op.qvel, model.nv),
            ("ctrl", op.ctrl, model.nu),
        ):
            if len(values) != n:
                raise ModelCardError(
                    f"{self.path}: operating_point.{field} has {len(values)} entries; the model has {n}"
                )


def _joint_id(model: mujoco.MjModel, name: str, where: str) -> int:
    jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
    if jid < 0:
        names = [model.joint(j).name for j in range(model.njnt)]
        raise ModelCardError(f"{where}: no joint {name!r} in the model; joints: {', '.join(names)}")
    if int(model.jnt_type[jid]) not in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)):
        raise ModelCardError(f"{where}: joint {name!r} is not a hinge or slide joint")
    return jid


def _check_signal(model: mujoco.MjModel, signal: str, where: str) -> None:
    ref = parse_signal(signal)
    if ref is None and signal.startswith("site:"):
        raise ModelCardError(f"{where}: expected site:<name>:x|y|z")
    if ref is None:
        raise ModelCardError(f"{where}: expected <joint>_pos, <joint>_vel or site:<name>:x|y|z")
    if ref.kind == "site" and mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, ref.name) < 0:
        raise ModelCardError(f"{where}: no site {ref.name!r} in the model")
    if ref.kind != "site":
        _joint_id(model, ref.name, where)


def _require(table: dict[str, Any], key: str, typ: type | tuple[type, ...], where: str) -> Any:
    if key not in table:
        raise ModelCardError(f"{where}: missing field {key!r}")
    value = table[key]
    if typ is dict:
        return as_table(value, f"{where}.{key}", ModelCardError)
    if not isinstance(value, typ) or (isinstance(value, bool) and typ is not bool):
        names = typ.__name__ if isinstance(typ, type) else " or ".join(t.__name__ for t in typ)
        raise ModelCardError(f"{where}.{key}: expected {names}, got {shown(value)}")
    return value


_FIELDS = {
    "": {"schema", "env_id", "description", "operating_point", "observation", "termination",
         "terminate_on_nonfinite", "tuning", "region", "rescue", "paper", "reward", "model", "perturbation",
         "balance"},
    "reward": {"alive", "failure"},
    "model": {"mjcf", "frame_skip", "max_episode_steps"},
    "operating_point": {"name", "qpos", "qvel", "ctrl", "note"},
    "observation": {"name", "source", "joint", "transform", "clip", "unit", "description"},
    "termination": {"signal", "low", "high", "interval", "description"},
    "tuning.loop": {"name", "signal", "rate_signal", "actuators", "core"},
    "perturbation": {"name", "kind", "direction", "limit", "unit", "description"},
    "balance": {"feet", "bend", "hips", "ankles", "height", "pitch", "description"},
    "paper": {"win_target", "episodes_to_5_wins", "episodes_to_average", "savings_percent"},
}  # fmt: skip
"""The fields each table of a model card may hold (``""``: the top level); anything else is refused."""


def _known(table: dict[str, Any], kind: str, where: str) -> dict[str, Any]:
    """``table`` when it holds only the fields of :data:`_FIELDS` ``[kind]`` (a typo is no silent default)."""
    allowed = _FIELDS[kind]
    unknown = sorted(set(table) - allowed)
    if unknown:
        names = [clip(k, 40) for k in unknown[:10]]
        raise ModelCardError(f"{where}: unknown field(s) {names}; allowed: {', '.join(sorted(allowed))}")
    return table


def _tables(value: Any, where: str) -> list[dict[str, Any]]:
    """A list of tables (``[[observation]]``, ``[[termination]]``, ``[[tuning.loop]]``)."""
    if not isinstance(value, list):
        raise ModelCardError(f"{where}: expected a list of tables ([[...]]), got {shown(value)}")
    return [as_table(t, f"{where}[{i}]", ModelCardError) for i, t in enumerate(value)]


def _floats(values: Any, where: str, length: int | None = None) -> tuple[float, ...]:
    """A list of finite numbers (``length`` of them when given)."""
    if not isinstance(values, list) or (length is not None and len(values) != length):
        count = "a list of numbers" if length is None else f"a list of {length} numbers"
        raise ModelCardError(f"{where}: expected {count}, got {shown(values)}")
    return tuple(number(v, where, ModelCardError) for v in values)


def _bound(value: Any, where: str) -> float:
    """A limit: a number, or ``inf``/``-inf`` (also as the strings ``"inf"``/``"-inf"``); never NaN."""
    if isinstance(value, str) and value in ("inf", "-inf"):
        return float(value)
    return number(value, where, ModelCardError, finite=False)


def _parse_observation(data: dict[str, Any], path: str) -> list[ObservationVariable]:
    obs: list[ObservationVariable] = []
    for i, t in enumerate(_tables(_require(data, "observation", list, path), f"{path}: observation")):
        where = f"{path}: observation[{i}]"
        _known(t, "observation", where)
        source = _require(t, "source", str, where)
        if source not in OBS_SOURCES:
            raise ModelCardError(f"{where}.source: {source!r}; allowed: {', '.join(OBS_SOURCES)}")
        transform = t.get("transform", "identity")
        if transform not in OBS_TRANSFORMS:
            raise ModelCardError(
                f"{where}.transform: {shown(transform)}; allowed: {', '.join(OBS_TRANSFORMS)}"
            )
        clip = None
        if "clip" in t:
            lo, hi = _floats(t["clip"], f"{where}.clip", length=2)
            if not lo < hi:
                raise ModelCardError(f"{where}.clip: low ({lo}) must be below high ({hi})")
            clip = (lo, hi)
        obs.append(
            ObservationVariable(
                name=check_name(_require(t, "name", str, where), f"{where}.name", ModelCardError, dots=False),
                source=source,
                joint=_require(t, "joint", str, where),
                transform=transform,
                clip=clip,
                unit=text(t.get("unit", ""), f"{where}.unit", ModelCardError),
                description=text(t.get("description", ""), f"{where}.description", ModelCardError),
            )
        )
    return obs


def _parse_tuning(data: dict[str, Any], path: str) -> tuple[tuple[TuningLoop, ...], bool]:
    table = as_table(data.get("tuning", {}), f"{path}: tuning", ModelCardError)
    unknown = sorted(set(table) - {"refine_on_env", "loop"})
    if unknown:
        raise ModelCardError(f"{path}: tuning: unknown field(s) {unknown}; allowed: refine_on_env, loop")
    refine = table.get("refine_on_env", False)
    if not isinstance(refine, bool):
        raise ModelCardError(f"{path}: tuning.refine_on_env: expected true or false, got {refine!r}")
    loops = []
    for i, lp in enumerate(_tables(table.get("loop", []), f"{path}: tuning.loop")):
        where = f"{path}: tuning.loop[{i}]"
        _known(lp, "tuning.loop", where)
        acts = _require(lp, "actuators", dict, where) if "actuators" in lp else {}
        weights = tuple(
            (str(k), number(v, f"{where}.actuators.{k}", ModelCardError)) for k, v in acts.items()
        )
        rate = lp.get("rate_signal")
        core = lp.get("core", True)
        if (rate is not None and not isinstance(rate, str)) or not isinstance(core, bool):
            raise ModelCardError(f"{where}: rate_signal must be a string and core true or false")
        loops.append(TuningLoop(_require(lp, "name", str, where), _require(lp, "signal", str, where),
                                rate, weights, core))  # fmt: skip
    return tuple(loops), refine


def _parse_region(data: dict[str, Any], path: str, names: list[str]) -> tuple[str, tuple[str, ...]]:
    table = as_table(data.get("region", {}), f"{path}: region", ModelCardError)
    unknown = sorted(set(table) - {"method", "variables"})
    if unknown:
        raise ModelCardError(f"{path}: region: unknown field(s) {unknown}; allowed: method, variables")
    method = table.get("method", "lyapunov")
    if method not in REGION_METHODS:
        raise ModelCardError(f"{path}: region.method: {method!r}; allowed: {', '.join(REGION_METHODS)}")
    variables = table.get("variables", [])
    ok = isinstance(variables, list) and all(isinstance(v, str) and v in names for v in variables)
    if not ok or (method == "simulation" and len(variables) != 2):
        raise ModelCardError(
            f"{path}: region.variables: {variables!r}; expected two observation names (a joint position "
            "and its rate), which the simulation method needs"
        )
    return str(method), tuple(variables)


def _parse_rescue(data: dict[str, Any], path: str, names: list[str]) -> RescueDomain | None:
    if "rescue" not in data:
        return None
    w = f"{path}: rescue"
    table = as_table(data["rescue"], w, ModelCardError)
    unknown = sorted(set(table) - {"variables", "half_range", "cells", "guard"})
    if unknown:
        raise ModelCardError(f"{w}: unknown field(s) {unknown}; allowed: variables, half_range, cells, guard")
    variables = table.get("variables")
    if (
        not isinstance(variables, list)
        or not 1 <= len(variables) <= 4
        or not all(v in names for v in variables)
    ):
        raise ModelCardError(f"{w}.variables: {shown(variables)}; expected 1 to 4 observation names")
    k = len(variables)
    half, cells = table.get("half_range"), table.get("cells")
    if not isinstance(half, list) or len(half) != k or not isinstance(cells, list) or len(cells) != k:
        raise ModelCardError(f"{w}: expected half_range and cells with {k} entries each")
    half_range = tuple(number(v, f"{w}.half_range", ModelCardError, low=0.0, low_open=True) for v in half)
    n_cells = tuple(integer(v, f"{w}.cells", ModelCardError, low=2, high=400) for v in cells)
    guard_t = as_table(table.get("guard", {}), f"{w}.guard", ModelCardError)
    for g in guard_t:
        if g not in names or g in variables:
            raise ModelCardError(f"{w}.guard.{g}: expected an observation name that is not a grid variable")
    guard = tuple(
        (str(g), number(v, f"{w}.guard.{g}", ModelCardError, low=0.0, low_open=True))
        for g, v in guard_t.items()
    )
    return RescueDomain(tuple(str(v) for v in variables), half_range, n_cells, guard)


def _parse_perturbations(data: dict[str, Any], path: str) -> tuple[Perturbation, ...]:
    out: list[Perturbation] = []
    for i, t in enumerate(_tables(data.get("perturbation", []), f"{path}: perturbation")):
        where = f"{path}: perturbation[{i}]"
        _known(t, "perturbation", where)
        name = check_name(_require(t, "name", str, where), f"{where}.name", ModelCardError)
        if name in [p.name for p in out]:
            raise ModelCardError(f"{where}.name: {name!r} is repeated; perturbation names must be unique")
        kind = t.get("kind")
        if kind not in PERTURBATION_KINDS:
            raise ModelCardError(f"{where}.kind: {shown(kind)}; allowed: {', '.join(PERTURBATION_KINDS)}")
        table = as_table(_require(t, "direction", dict, where), f"{where}.direction", ModelCardError)
        direction = tuple(
            (str(j), number(v, f"{where}.direction.{clip(str(j), 40)}", ModelCardError))
            for j, v in table.items()
        )
        if not any(v != 0.0 for _, v in direction):
            raise ModelCardError(f"{where}.direction: expected at least one joint with a nonzero weight")
        limit = number(_require(t, "limit", (int, float), where), f"{where}.limit", ModelCardError,
                       low=0.0, low_open=True)  # fmt: skip
        out.append(
            Perturbation(
                name=name,
                kind=str(kind),
                direction=direction,
                limit=limit,
                unit=text(t.get("unit", ""), f"{where}.unit", ModelCardError),
                description=text(t.get("description", ""), f"{where}.description", ModelCardError),
            )
        )
    return tuple(out)


def _names_list(value: Any, where: str) -> tuple[str, ...]:
    if not isinstance(value, list) or not value or not all(isinstance(v, str) and v for v in value):
        raise ModelCardError(f"{where}: expected a non-empty list of names, got {shown(value)}")
    return tuple(value)


def _parse_balance(data: dict[str, Any], path: str) -> Balance | None:
    if "balance" not in data:
        return None
    where = f"{path}: balance"
    t = _known(_require(data, "balance", dict, path), "balance", where)
    bend = as_table(t.get("bend", {}), f"{where}.bend", ModelCardError)
    return Balance(
        feet=_names_list(t.get("feet"), f"{where}.feet"),
        bend=tuple(
            (str(j), number(v, f"{where}.bend.{clip(str(j), 40)}", ModelCardError, low=-math.pi,
                            high=math.pi))
            for j, v in bend.items()
        ),
        hips=_names_list(t.get("hips"), f"{where}.hips"),
        ankles=_names_list(t.get("ankles"), f"{where}.ankles"),
        height=text(_require(t, "height", str, where), f"{where}.height", ModelCardError, empty=False),
        pitch=text(_require(t, "pitch", str, where), f"{where}.pitch", ModelCardError, empty=False),
        description=text(t.get("description", ""), f"{where}.description", ModelCardError),
    )


def _parse_reward(data: dict[str, Any], path: str) -> RewardFacts:
    if "reward" not in data:
        return RewardFacts()
    where = f"{path}: reward"
    table = _known(_require(data, "reward", dict, path), "reward", where)
    alive = None
    if "alive" in table:
        alive = number(_require(table, "alive", (int, float), where), f"{where}.alive", ModelCardError)
    failure = None
    if "failure" in table:
        terms = table["failure"]
        if not isinstance(terms, list) or not all(isinstance(t, str) and t for t in terms):
            raise ModelCardError(
                f"{where}.failure: expected a list of step-info names (e.g. ['reward_forward']), "
                f"got {shown(terms)}"
            )
        failure = tuple(terms)
    return RewardFacts(alive, failure)


def _parse_model(data: dict[str, Any], path: str) -> CardModel | None:
    if "model" not in data:
        return None
    where = f"{path}: model"
    table = _known(_require(data, "model", dict, path), "model", where)
    mjcf = text(_require(table, "mjcf", str, where), f"{where}.mjcf", ModelCardError, empty=False)
    if "\0" in mjcf:
        raise ModelCardError(f"{where}.mjcf: {shown(mjcf)} is no path; expected the MJCF file's path")
    if not mjcf.lower().endswith(MJCF_SUFFIXES):
        raise ModelCardError(
            f"{where}.mjcf: {shown(mjcf)}; expected an MJCF file (.xml) or a compiled model (.mjb)"
        )
    frame_skip = integer(table.get("frame_skip", 1), f"{where}.frame_skip", ModelCardError, low=1, high=1000)
    steps = integer(
        table.get("max_episode_steps", 1000), f"{where}.max_episode_steps", ModelCardError, low=1, high=10**7
    )
    full = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(path)), mjcf))  # no link is followed
    return CardModel(full, frame_skip, steps)


def _parse_paper(data: dict[str, Any], path: str) -> PaperNumbers | None:
    if "paper" not in data:
        return None
    where = f"{path}: paper"
    table = _known(_require(data, "paper", dict, path), "paper", where)

    def pair(key: str, a: str, b: str, episodes: bool) -> tuple[float, float]:
        sub = _require(table, key, dict, where)
        w = f"{where}.{key}"
        if episodes:  # counts of episodes
            first, second = (
                integer(_require(sub, k, int, w), f"{w}.{k}", ModelCardError, low=0) for k in (a, b)
            )
            return first, second
        x, y = (number(_require(sub, k, (int, float), w), f"{w}.{k}", ModelCardError) for k in (a, b))
        return x, y

    wins = pair("episodes_to_5_wins", "coached", "uncoached", True)
    average = pair("episodes_to_average", "coached", "uncoached", True)
    savings = pair("savings_percent", "wins", "average", False)
    target = number(_require(table, "win_target", (int, float), where), f"{where}.win_target", ModelCardError)
    return PaperNumbers(target, int(wins[0]), int(wins[1]), int(average[0]), int(average[1]), *savings)


def parse_card(data: dict[str, Any], path: str) -> ModelCard:
    """Build a :class:`ModelCard` from parsed TOML, validating every field.

    Raises
    ------
    ModelCardError
        Naming the field and what is allowed.
    """
    as_table(data, path, ModelCardError, "a table (parsed TOML)")
    schema = data.get("schema")
    if schema != CARD_SCHEMA:
        raise ModelCardError(f"{path}: schema is {shown(schema)}; expected {CARD_SCHEMA!r}")
    _known(data, "", path)
    env_id = check_name(_require(data, "env_id", str, path), f"{path}: env_id", ModelCardError)
    w = f"{path}: operating_point"
    opt = _known(_require(data, "operating_point", dict, path), "operating_point", w)
    op = CardOperatingPoint(
        name=text(opt.get("name", "operating point"), f"{w}.name", ModelCardError),
        qpos=_floats(_require(opt, "qpos", list, w), f"{w}.qpos"),
        qvel=_floats(_require(opt, "qvel", list, w), f"{w}.qvel"),
        ctrl=_floats(_require(opt, "ctrl", list, w), f"{w}.ctrl"),
        note=text(opt.get("note", ""), f"{w}.note", ModelCardError),
    )
    obs = _parse_observation(data, path)
    names = [v.name for v in obs]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise ModelCardError(f"{path}: observation names must be unique; repeated: {dupes}")
    term: list[TerminationLimit] = []
    for i, t in enumerate(_tables(data.get("termination", []), f"{path}: termination")):
        where = f"{path}: termination[{i}]"
        _known(t, "termination", where)
        interval = t.get("interval", "closed")
        if interval not in INTERVALS:
            raise ModelCardError(f"{where}.interval: {shown(interval)}; allowed: closed, open")
        low = _bound(t.get("low", "-inf"), f"{where}.low")
        high = _bound(t.get("high", "inf"), f"{where}.high")
        if not low < high:
            raise ModelCardError(f"{where}: low ({low}) must be below high ({high})")
        term.append(
            TerminationLimit(
                signal=_require(t, "signal", str, where),
                low=low,
                high=high,
                interval=interval,
                description=text(t.get("description", ""), f"{where}.description", ModelCardError),
            )
        )
    tuning, refine = _parse_tuning(data, path)
    region = _parse_region(data, path, names)
    for lp in tuning:
        for name in (lp.signal, lp.rate_signal):
            if name is not None and name not in names:
                raise ModelCardError(f"{path}: tuning.loop {lp.name!r}: {name!r} is not an observation name")
    return ModelCard(
        env_id=env_id,
        description=text(data.get("description", ""), f"{path}: description", ModelCardError),
        operating_point=op,
        observation=tuple(obs),
        termination=tuple(term),
        terminate_on_nonfinite=flag(
            data.get("terminate_on_nonfinite", True), f"{path}: terminate_on_nonfinite", ModelCardError
        ),
        path=path,
        tuning=tuning,
        refine_on_env=refine,
        region_method=region[0],
        region_variables=region[1],
        paper=_parse_paper(data, path),
        rescue=_parse_rescue(data, path, names),
        reward=_parse_reward(data, path),
        model=_parse_model(data, path),
        perturbation=_parse_perturbations(data, path),
        balance=_parse_balance(data, path),
    )


def load_card(path: str | Path) -> ModelCard:
    """Read and validate one model card file.

    Raises
    ------
    ModelCardError
    """
    return parse_card(read_toml(path, "model card", ModelCardError), str(path))


def find_card(env_id: str) -> ModelCard | None:
    """The model card of ``env_id`` (the user's folder first, then the shipped one), or None.

    An ``env_id`` that is no name of :data:`pidlab.checks.NAME_RULE` has no card (its file name
    would leave ``models/``).

    Raises
    ------
    ModelCardError
        The card cannot be read (a loop of symbolic links, no permission) or is malformed, or it
        is for another env (its ``env_id`` is not the one its file is named after).
    """
    if not is_name(env_id):
        return None
    path_under(models_dir(), f"{env_id}.toml", error=ModelCardError)  # the name stays inside models/
    path = find_data_file("models", f"{env_id}.toml")  # the user's card, else the shipped one
    if not (path.exists() or path.is_symlink()):  # a link to nowhere, or a loop, is no missing card
        return None
    card = load_card(path)
    if card.env_id != env_id:
        raise ModelCardError(
            f"{path}: env_id = {card.env_id!r}, but the card is for {env_id} (its file name); "
            f"expected env_id = {env_id!r}"
        )
    return card


def card_for_mjcf(mjcf: str | Path) -> ModelCard | None:
    """The model card whose ``[model] mjcf`` is the file ``mjcf`` (the user's folder first), or None.

    Only cards whose text mentions the file's name are read; such a card that is malformed is an
    error, not a silent miss.

    Raises
    ------
    ModelCardError
        A card naming the file is malformed, or is named after another env than its ``env_id``.
    """
    target = Path(mjcf)
    for path in data_files("models", "*.toml"):
        try:
            raw = read_file(path).decode("utf-8")
        except (OSError, UnicodeDecodeError):  # not a card this file could be described by
            continue
        if "mjcf" not in raw or target.name not in raw:
            continue
        card = load_card(path)
        if card.model is None or not _same_file(card.model.mjcf, target):
            continue
        if card.env_id != path.stem:
            raise ModelCardError(
                f"{path}: env_id = {card.env_id!r}, but the card is for {path.stem} (its file name)"
            )
        return card
    return None


def _same_file(a: str | Path, b: str | Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except (OSError, ValueError):
        return os.path.normpath(os.path.abspath(a)) == os.path.normpath(os.path.abspath(b))
