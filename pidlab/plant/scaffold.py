"""``pidlab init``: the files that make your MJCF a pidlab env, written for you to edit.

From an MJCF file and an env id, :func:`scaffold` writes (as texts, nothing on disk):

- ``models/ID.toml``: the model card. Its operating point comes from a keyframe (``--keyframe``,
  else the model's first) or ``qpos0``. Its signals are every hinge and slide joint's position and
  velocity; termination limits hold each joint within its range (an unlimited hinge within
  ±0.2 rad, a fall); one tuning loop per joint, the joints no actuator drives first (a pendulum's
  pole); an alive reward of 1 per step; a ``[model]`` table naming the MJCF file (where it is:
  nothing is copied, so its includes and meshes keep working), the frame skip and the time limit.
- ``coach/ID.toml``: the recipe: PPO and SAC tables with the RL Baselines3 Zoo's pendulum values,
  each field explained, and a ``[pipeline]`` table for ``pidlab run ID``.
- ``ID_env.py`` (its module name from the id): registers ``ID`` as a
  :class:`pidlab.plant.card_env.CardEnv` of the card.
- ``pidlab.toml``: the project file (:mod:`pidlab.project`): every ``pidlab`` command run in that
  folder finds the env module, the card, the recipe and the specs you tune.

:func:`write_scaffold` writes them (atomically, never over an existing file unless ``force``).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from pidlab.checks import check_name
from pidlab.errors import ArgumentError
from pidlab.files import atomic_write_text, check_output_folder

HINGE_LIMIT = 0.2
"""The healthy range of an unlimited hinge joint in a scaffold's card, rad (edit it)."""

CONTROL_PERIOD = 0.02
"""The control period a scaffold aims at by default, s (InvertedPendulum-v5's: 2 steps of 10 ms)."""

GUARD_SLIDE, GUARD_HINGE, GUARD_RATE = 0.5, 0.1, 0.5
"""A scaffold's rescue guard: half-widths for a slide (m), a hinge (rad) and their rates (per s)."""

MAX_EPISODE_STEPS = 1000
"""A scaffold's time limit, in control periods (the paper envs')."""


Joint = tuple[str, bool, bool, "tuple[float, float] | None"]
"""A hinge or slide joint: name, is a hinge, is driven by an actuator, its range (None: unlimited)."""


@dataclass(frozen=True)
class Scaffold:
    """The files of a scaffold: relative path -> text; ``module``: the env module's import name."""

    env_id: str
    module: str
    files: dict[str, str]


def module_name(env_id: str) -> str:
    """The env module's name for ``env_id``: lower case, ``_`` for every other character, ``_env``."""
    return re.sub(r"[^a-z0-9_]", "_", env_id.lower()).strip("_") + "_env"


def scaffold(
    mjcf: str | Path,
    env_id: str,
    keyframe: str | None = None,
    frame_skip: int | None = None,
    out: str | Path = ".",
) -> Scaffold:
    """The scaffold of ``mjcf`` registered as ``env_id``, to be written under ``out`` (module docstring).

    Parameters
    ----------
    mjcf : str or Path
        The MJCF file; the card names it relative to ``out/models``.
    env_id : str
    keyframe : str, optional
        The operating point's keyframe (default: the model's first, else ``qpos0``).
    frame_skip : int, optional
        MuJoCo steps per control period (default: the period nearest :data:`CONTROL_PERIOD`).
    out : str or Path
        The folder the scaffold goes to.

    Raises
    ------
    ArgumentError
        An env id that is no name, a keyframe the model lacks, a model without actuators or
        without a hinge or slide joint, a frame skip below 1.
    ModelCompileError
        MuJoCo cannot load the file.
    """
    from pidlab.checks import integer
    from pidlab.plant.model import compile_mjcf

    check_name(env_id, "--env-id", ArgumentError)
    path = Path(mjcf)
    if path.suffix.lower() not in (".xml", ".mjcf"):
        raise ArgumentError(f"{mjcf}: expected an MJCF file (.xml)")
    if frame_skip is not None:
        frame_skip = integer(frame_skip, "frame_skip", ArgumentError, low=1, high=1000, param="frame_skip")
    model = compile_mjcf(path)
    if frame_skip is None:
        frame_skip = max(1, round(CONTROL_PERIOD / float(model.opt.timestep)))
    if model.nu == 0:
        raise ArgumentError(f"{mjcf}: the model has no actuator; a coach needs one to act with")
    joints = _joints(model)
    if not joints:
        raise ArgumentError(
            f"{mjcf}: the model has no hinge or slide joint; a card names its signals by them"
        )
    qpos, qvel, ctrl, point = _operating_point(model, keyframe, str(mjcf))
    module = module_name(env_id)
    relative = os.path.relpath(os.path.abspath(path), os.path.abspath(Path(out) / "models"))
    card = _card(model, env_id, joints, (qpos, qvel, ctrl, point), path.name)
    card += _model_table(relative, frame_skip, float(model.opt.timestep))
    _check_card(card, env_id, model, frame_skip, str(mjcf))
    files = {
        f"models/{env_id}.toml": card,
        f"coach/{env_id}.toml": _recipe(env_id),
        f"{module}.py": _env_module(env_id),
        "pidlab.toml": _project(module),
    }
    return Scaffold(env_id, module, files)


def write_scaffold(s: Scaffold, out: str | Path, force: bool = False) -> list[Path]:
    """Write ``s`` under ``out``; the paths written.

    Raises
    ------
    ArgumentError
        A file exists and ``force`` is not set (nothing is written then).
    OutputError
        ``out`` (or its ``models``/``coach`` folder) is a file or cannot be written.
    """
    root = check_output_folder(out, param="out")
    for sub in ("models", "coach"):
        check_output_folder(root / sub, param="out")
    targets = {root / rel: text for rel, text in s.files.items()}
    existing = [p for p in targets if os.path.lexists(p)]
    if existing and not force:
        raise ArgumentError(
            f"{existing[0]} exists (and {len(existing) - 1} other file(s) of the scaffold); nothing was "
            "written. Edit it, choose another --out, or pass --force to overwrite"
        )
    for p, text in targets.items():
        p.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(p, text)
    return list(targets)


def signal_names(joints: list[Joint]) -> dict[str, str]:
    """Joint name -> the base of its signals' names (``<base>_pos``, ``<base>_vel``), unique.

    A joint's name as it is when it is a signal name already (letters, digits, ``_``, ``-``);
    else each other character becomes ``_`` (``"pole angle"`` -> ``pole_angle``), and a clash is
    numbered. The card's ``joint`` fields keep the MJCF's own names.
    """
    out: dict[str, str] = {}
    for name, *_ in joints:
        base = re.sub(r"[^A-Za-z0-9_-]", "_", name)[:56]
        base = base if base[:1].isalnum() else f"j{base}"[:56]
        unique, k = base, 1
        while unique in out.values():
            unique, k = f"{base[:52]}_{k}", k + 1
        out[name] = unique
    return out


def _joints(model: mujoco.MjModel) -> list[Joint]:
    """``(name, hinge, actuated, range)`` of every hinge and slide joint, the unactuated first."""
    driven = {
        int(model.actuator_trnid[a, 0])
        for a in range(model.nu)
        if int(model.actuator_trntype[a]) == int(mujoco.mjtTrn.mjTRN_JOINT)
    }
    out = []
    for j in range(model.njnt):
        kind = int(model.jnt_type[j])
        if kind not in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)):
            continue
        name = model.joint(j).name
        if not name:
            continue
        limited = bool(model.jnt_limited[j])
        rng = (float(model.jnt_range[j, 0]), float(model.jnt_range[j, 1])) if limited else None
        out.append((name, kind == int(mujoco.mjtJoint.mjJNT_HINGE), j in driven, rng))
    return sorted(out, key=lambda j: j[2])  # stable: unactuated joints first, model order kept


def _operating_point(
    model: mujoco.MjModel, keyframe: str | None, where: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    if keyframe is None and model.nkey == 0:
        return model.qpos0.copy(), np.zeros(model.nv), np.zeros(model.nu), "qpos0"
    k = 0 if keyframe is None else mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_KEY, keyframe)
    if k < 0:
        names = [model.key(i).name for i in range(model.nkey)] or ["none"]
        raise ArgumentError(f"{where}: no keyframe {keyframe!r}; keyframes: {', '.join(names)}")
    key = model.key(k)
    return key.qpos.copy(), key.qvel.copy(), key.ctrl.copy(), f"keyframe {key.name or k}"


def _floats(values: np.ndarray) -> str:
    return "[" + ", ".join(repr(float(v)) for v in values) + "]"


def _card(
    model: mujoco.MjModel,
    env_id: str,
    joints: list[Joint],
    operating_point: tuple[np.ndarray, np.ndarray, np.ndarray, str],
    xml: str,
) -> str:
    qpos, qvel, ctrl, point = operating_point
    sig = signal_names(joints)
    lines = [
        f"# Model card of {env_id}, written by pidlab init from {xml!r}: edit it, then run pidlab.",
        "# Every field is explained in docs/linearization.md (Model cards).",
        'schema = "pidlab.model-card/1"',
        f'env_id = "{env_id}"',
        f"description = {_toml_string(f'{env_id}: {xml}, {len(joints)} joint(s), {model.nu} actuator(s).')}",
        "",
        "[operating_point]   # where the coach holds the system",
        f"name = {_toml_string(point)}",
        f"qpos = {_floats(qpos)}",
        f"qvel = {_floats(qvel)}",
        f"ctrl = {_floats(ctrl)}",
        f"note = {_toml_string(f'from the model’s {point}')}",
    ]
    for kind, unit_of in (("pos", lambda h: "rad" if h else "m"), ("vel", lambda h: "rad/s" if h else "m/s")):
        for name, hinge, _, _ in joints:
            source = "qpos" if kind == "pos" else "qvel"
            lines += [
                "",
                "[[observation]]",
                f"name = {_toml_string(f'{sig[name]}_{kind}')}",
                f'source = "{source}"',
                f"joint = {_toml_string(name)}",
                f'unit = "{unit_of(hinge)}"',
            ]
    lines += ["", "# EDIT: the healthy range of each signal; an episode ends when one leaves it."]
    for name, hinge, _, rng in joints:
        if rng is None and not hinge:
            continue
        low, high = rng if rng is not None else (-HINGE_LIMIT, HINGE_LIMIT)
        why = "the joint's range" if rng is not None else f"a fall: +-{HINGE_LIMIT} rad from upright"
        lines += [
            "",
            "[[termination]]",
            f"signal = {_toml_string(f'{name}_pos')}",  # a joint's position, by the MJCF's name
            f"low = {low!r}",
            f"high = {high!r}",
            f'description = "{why}"',
        ]
    lines += [
        "",
        "# One loop per joint, the joints no actuator drives first; the actuators' weights come",
        "# from the LQR start ({}). Loops with core = false are dropped by the weak preset.",
        "[tuning]",
        "refine_on_env = false",
    ]
    for i, (name, _, actuated, _) in enumerate(joints):
        lines += [
            "",
            "[[tuning.loop]]",
            f"name = {_toml_string(sig[name])}",
            f"signal = {_toml_string(f'{sig[name]}_pos')}",
            f"rate_signal = {_toml_string(f'{sig[name]}_vel')}",
            "actuators = {}",
            f"core = {'false' if actuated and i > 0 else 'true'}",
        ]
    lines += [
        "",
        "[region]",
        'method = "lyapunov"   # the certified level set of the linear model',
        *_rescue_table(joints),
        "",
        "# What the env pays (pidlab.plant.card_env.CardEnv pays these).",
        "[reward]",
        "alive = 1.0   # per step that does not fail",
        "failure = []  # a failing step pays 0",
        "",
    ]
    return "\n".join(lines)


def _rescue_table(joints: list[Joint]) -> list[str]:
    """The rescue region's domain: a grid over the first joint's position and rate, the rest guarded.

    The guard box holds every other joint near the operating point (a slide within 0.5 m, a hinge
    within 0.1 rad, their rates within 0.5): the region is validated only with them there, and the
    coach takes over when one leaves it. Without it, they would be taken at the operating point
    and the region would claim states it was never tried from (a cart moving fast).
    """
    sig = signal_names(joints)
    name, _, _, rng = joints[0]
    half = min(abs(rng[0]), abs(rng[1])) if rng is not None else HINGE_LIMIT
    half = half if half > 0 else HINGE_LIMIT  # a range that starts at the joint's zero
    guard = []
    for other, other_hinge, _, other_rng in joints[1:]:
        width = GUARD_HINGE if other_hinge else GUARD_SLIDE
        if other_rng is not None:
            width = min(width, (other_rng[1] - other_rng[0]) / 4)
        guard += [f"{sig[other]}_pos = {width:g}", f"{sig[other]}_vel = {GUARD_RATE:g}"]
    return [
        "",
        "# The rescue region (pidlab rescue): a grid over the first joint's position and rate; the other",
        "# joints are drawn within the guard box, and the coach takes over when one leaves it. EDIT: widen",
        "# the guard where the coach still rescues from there (pidlab rescue validates it).",
        "[rescue]",
        f'variables = ["{sig[name]}_pos", "{sig[name]}_vel"]',
        f"half_range = [{half:g}, {10 * half:g}]",
        "cells = [40, 40]",
        f"guard = {{ {', '.join(guard)} }}" if guard else "guard = {}",
    ]


def _recipe(env_id: str) -> str:
    from pidlab.data import shipped_dir

    text = (shipped_dir("coach") / "InvertedPendulum-v5.toml").read_text()
    body = text[text.index("[normalize]") :]
    body = re.sub(r'condition = "[^"]*"', 'condition = "rescue-terminal"', body)
    body = re.sub(r'preset = "[^"]*"', 'preset = "robust"', body)
    body = re.sub(
        r"(?ms)^# What `pidlab run .*?(?=^\[pipeline\])", _PIPELINE_NOTE.format(env_id=env_id), body
    )
    body = body.replace(
        "[win]\n",
        "[win]   # EDIT: a score an episode reaches once the task is learnt (800 of 1000 alive steps)\n",
        1,
    )
    head = (
        f"# Training recipe of {env_id}, written by pidlab init: the RL Baselines3 Zoo's pendulum values.\n"
        "# Every field is explained in docs/reference/recipe.md.\n"
        'schema = "pidlab.recipe/1"\n'
        f'env_id = "{env_id}"\n'
        f'description = "{env_id}: PPO (and SAC) with the zoo\'s pendulum values; edit for your task."\n'
        'algo = "ppo"\nsteps = 100000\nn_envs = 1\nvec_env = "dummy"\nseed = 0\nthreads = 1\n\n'
    )
    return head + body


_PIPELINE_NOTE = """\
# What `pidlab run {env_id}` does: auto-tune a coach (the robust preset), derive its certified core
# and its rescue region, then train the agent of this recipe with and without it on a short budget.
# The coach coaches as the condition rescue-terminal says: its rescue region shields the agent, and a
# takeover ends the agent's episode as a failure. Other conditions: coach/conditions.toml.
"""


def _check_card(text: str, env_id: str, model: mujoco.MjModel, frame_skip: int, where: str) -> None:
    """Refuse to write a card that would not load on its own model (a scaffold that fails later)."""
    import tomllib

    from pidlab.errors import ModelCardError
    from pidlab.plant.card import parse_card

    try:
        parse_card(tomllib.loads(text), f"models/{env_id}.toml").check_against(model, frame_skip)
    except (ModelCardError, tomllib.TOMLDecodeError) as exc:
        raise ArgumentError(f"{where}: the scaffold cannot describe this model: {exc}") from None


def _model_table(relative: str, frame_skip: int, timestep: float) -> str:
    period = frame_skip * timestep
    return "\n".join([
        "",
        "# The MJCF file (relative to this card's folder) and how its env steps: the control period is",
        f"# frame_skip x the model's timestep ({frame_skip} x {timestep:g} s = {period:g} s).",
        "[model]",
        f"mjcf = {_toml_string(relative)}",
        f"frame_skip = {frame_skip}",
        f"max_episode_steps = {MAX_EPISODE_STEPS}   # an episode's time limit, in control periods",
        "",
    ])  # fmt: skip


def _toml_string(value: str) -> str:
    """``value`` as a TOML basic string (quotes, backslashes and control characters escaped)."""
    out = value.replace("\\", "\\\\").replace('"', '\\"')
    return '"' + "".join(c if c.isprintable() else f"\\U{ord(c):08x}" for c in out) + '"'


def _project(module: str) -> str:
    from pidlab.project import PROJECT_SCHEMA

    return "\n".join([
        "# pidlab project file, written by pidlab init: every pidlab command run in this folder reads it.",
        "# Every field is explained in docs/tutorials/your-own-robot.md.",
        f'schema = "{PROJECT_SCHEMA}"',
        f'gym_packages = ["{module}"]   # modules that register your envs (found in this folder)',
        'models = "models"   # your model cards, searched before the shipped ones',
        'tuning = "tuning"   # your coach specs (pidlab tune writes them here)',
        'coach = "coach"     # your recipes (conditions.toml falls back to the shipped one)',
        "",
    ])  # fmt: skip


def _env_module(env_id: str) -> str:
    return f'''"""{env_id}: written by pidlab init. Import it to register the env (pidlab.toml names it).

The env is a pidlab.plant.card_env.CardEnv: the MJCF file that the card models/{env_id}.toml
names in its [model] table, observed, ended and paid as the card says, with the card's frame skip
and time limit. For another reward, subclass CardEnv, override its reward(), and register the
subclass here instead.
"""

from pathlib import Path

import gymnasium

from pidlab.plant.card import load_card

CARD = Path(__file__).absolute().parent / "models" / "{env_id}.toml"  # beside this module (user code)

gymnasium.register(
    "{env_id}",
    entry_point="pidlab.plant.card_env:CardEnv",
    kwargs={{"card": str(CARD)}},
    max_episode_steps=load_card(CARD).model.max_episode_steps,
)
'''
