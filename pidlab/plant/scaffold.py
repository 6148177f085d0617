"""``pidlab init``: the files that make your MJCF a pidlab env, written for you to edit.

From an MJCF file and an env id, :func:`scaffold` writes (as texts, nothing on disk):

- ``models/ID.toml``: the model card. Its operating point comes from a keyframe (``--keyframe``,
  else the model's first) or ``qpos0``. Its signals are every hinge and slide joint's position and
  velocity; termination limits hold each joint within its range (an unlimited hinge within
  ±0.2 rad, a fall); one tuning loop per joint, the joints no actuator drives first (a pendulum's
  pole); an alive reward of 1 per step.
- ``coach/ID.toml``: the recipe: PPO and SAC tables with the RL Baselines3 Zoo's pendulum values,
  each field explained, and a ``[pipeline]`` table for ``pidlab run ID``.
- ``ID_env.py`` (its module name from the id): registers ``ID`` as a
  :class:`pidlab.plant.card_env.CardEnv` of the MJCF and the card.

:func:`write_scaffold` writes them (atomically, never over an existing file unless ``force``).
"""

from __future__ import annotations

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


def scaffold(mjcf: str | Path, env_id: str, keyframe: str | None = None) -> Scaffold:
    """The scaffold of ``mjcf`` registered as ``env_id`` (see the module docstring).

    Raises
    ------
    ArgumentError
        An env id that is no name, a keyframe the model lacks, a model without actuators or
        without a hinge or slide joint.
    ModelCompileError
        MuJoCo cannot load the file.
    """
    from pidlab.plant.model import load_model

    check_name(env_id, "--env-id", ArgumentError)
    path = Path(mjcf)
    if path.suffix.lower() not in (".xml", ".mjcf"):
        raise ArgumentError(f"{mjcf}: expected an MJCF file (.xml)")
    model = load_model(path).model
    if model.nu == 0:
        raise ArgumentError(f"{mjcf}: the model has no actuator; a coach needs one to act with")
    joints = _joints(model)
    if not joints:
        raise ArgumentError(
            f"{mjcf}: the model has no hinge or slide joint; a card names its signals by them"
        )
    qpos, qvel, ctrl, point = _operating_point(model, keyframe, str(mjcf))
    module = module_name(env_id)
    card = _card(model, env_id, joints, qpos, qvel, ctrl, point, path.name)
    env = _env_module(env_id, path.name)
    return Scaffold(
        env_id,
        module,
        {f"models/{env_id}.toml": card, f"coach/{env_id}.toml": _recipe(env_id), f"{module}.py": env},
    )


def write_scaffold(s: Scaffold, out: str | Path, mjcf: str | Path, force: bool = False) -> list[Path]:
    """Write ``s`` under ``out`` with a copy of ``mjcf`` beside the env module; the paths written.

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
    copy = root / Path(mjcf).name
    existing = [
        p for p in [*targets, copy] if p.exists() and not (p == copy and p.resolve() == Path(mjcf).resolve())
    ]
    if existing and not force:
        raise ArgumentError(
            f"{existing[0]} exists (and {len(existing) - 1} other file(s) of the scaffold); nothing was "
            "written. Edit it, choose another --out, or pass --force to overwrite"
        )
    for p, text in targets.items():
        p.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(p, text)
    if copy.resolve() == Path(mjcf).resolve():
        return list(targets)
    atomic_write_text(copy, Path(mjcf).read_text())
    return [*targets, copy]


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
    qpos: np.ndarray,
    qvel: np.ndarray,
    ctrl: np.ndarray,
    point: str,
    xml: str,
) -> str:
    lines = [
        f"# Model card of {env_id}, written by pidlab init from {xml}: edit it, then run pidlab.",
        "# Every field is explained in docs/linearization.md (Model cards).",
        'schema = "pidlab.model-card/1"',
        f'env_id = "{env_id}"',
        f'description = "{env_id}: {xml}, {len(joints)} joint(s) as signals, {model.nu} actuator(s)."',
        "",
        "[operating_point]   # where the coach holds the system",
        f'name = "{point}"',
        f"qpos = {_floats(qpos)}",
        f"qvel = {_floats(qvel)}",
        f"ctrl = {_floats(ctrl)}",
        f'note = "from the model\'s {point}"',
    ]
    for kind, unit_of in (("pos", lambda h: "rad" if h else "m"), ("vel", lambda h: "rad/s" if h else "m/s")):
        for name, hinge, _, _ in joints:
            source = "qpos" if kind == "pos" else "qvel"
            lines += [
                "",
                "[[observation]]",
                f'name = "{name}_{kind}"',
                f'source = "{source}"',
                f'joint = "{name}"',
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
            f'signal = "{name}_pos"',
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
            f'name = "{name}"',
            f'signal = "{name}_pos"',
            f'rate_signal = "{name}_vel"',
            "actuators = {}",
            f"core = {'false' if actuated and i > 0 else 'true'}",
        ]
    lines += [
        "",
        "[region]",
        'method = "lyapunov"   # the certified level set of the linear model',
        "",
        "# What the env pays (pidlab.plant.card_env.CardEnv pays these).",
        "[reward]",
        "alive = 1.0   # per step that does not fail",
        "failure = []  # a failing step pays 0",
        "",
    ]
    return "\n".join(lines)


def _recipe(env_id: str) -> str:
    from pidlab.data import shipped_dir

    text = (shipped_dir("coach") / "InvertedPendulum-v5.toml").read_text()
    body = text[text.index("[normalize]") :]
    body = re.sub(r'condition = "[^"]*"', 'condition = "rescue-terminal"', body)
    body = re.sub(r'preset = "[^"]*"', 'preset = "robust"', body)
    head = (
        f"# Training recipe of {env_id}, written by pidlab init: the RL Baselines3 Zoo's pendulum values.\n"
        "# Every field is explained in docs/reference/recipe.md.\n"
        'schema = "pidlab.recipe/1"\n'
        f'env_id = "{env_id}"\n'
        f'description = "{env_id}: PPO (and SAC) with the zoo\'s pendulum values; edit for your task."\n'
        'algo = "ppo"\nsteps = 100000\nn_envs = 1\nvec_env = "dummy"\nseed = 0\nthreads = 1\n\n'
    )
    return head + body


def _env_module(env_id: str, xml: str) -> str:
    return f'''"""{env_id}: written by pidlab init. Import it to register the env (pidlab --gym-packages).

The env is a pidlab.plant.card_env.CardEnv: the MJCF below, observed, ended and paid as its card
models/{env_id}.toml says. For another reward, subclass CardEnv and override its reward().
"""

from pathlib import Path

import gymnasium

HERE = Path(__file__).absolute().parent  # the folder of this module (user code)

gymnasium.register(
    "{env_id}",
    entry_point="pidlab.plant.card_env:CardEnv",
    kwargs={{"xml_file": str(HERE / "{xml}"), "card": str(HERE / "models" / "{env_id}.toml"),
            "frame_skip": 2}},
    max_episode_steps=1000,
)
'''
