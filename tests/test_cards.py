"""Model cards against the real envs: observation map and termination rule, by name."""

from __future__ import annotations

import re

import gymnasium as gym
import numpy as np
import pytest

from pidlab.errors import ModelCardError, UnknownSignalError
from pidlab.plant.card import Signal, load_card, parse_card, parse_signal
from pidlab.plant.observation import CompiledCard, check_termination, observe
from tests.helpers import PAPER_ENVS


@pytest.mark.parametrize("env_id", PAPER_ENVS)
def test_observation_map_reproduces_env_observation(models, env_id):
    card = models[env_id].card
    assert card is not None
    env = gym.make(env_id)
    try:
        assert len(card.observation) == env.observation_space.shape[0]
        obs, _ = env.reset(seed=1)
        u = env.unwrapped
        checked = terminations = 0
        rng = np.random.default_rng(0)
        fast = CompiledCard(card, u.model)
        for _ in range(400):
            np.testing.assert_array_equal(observe(card, u.model, u.data), obs)
            np.testing.assert_array_equal(fast.observe(u.data), obs)
            checked += 1
            obs, _, terminated, truncated, _ = env.step(rng.uniform(-1, 1, env.action_space.shape))
            check = check_termination(card, u.model, u.data)
            assert check.terminated == terminated, (check, terminated)
            assert fast.terminated(u.data) == terminated
            if terminated or truncated:
                terminations += terminated
                obs, _ = env.reset(seed=int(rng.integers(1 << 30)))
        assert checked == 400
        assert terminations > 0  # random actions do end episodes: the rule was exercised
    finally:
        env.close()


def test_observation_names_are_unique_and_named_by_joint(models):
    hopper = models["Hopper-v5"].card
    assert "rootx_pos" not in hopper.observation_names  # Hopper's observation drops rootx
    assert hopper.observation_names[:2] == ("rootz_pos", "rooty_pos")
    assert hopper.variable("rooty_vel").clip == (-10.0, 10.0)
    with pytest.raises(UnknownSignalError, match="valid names: rootz_pos, rooty_pos"):
        hopper.variable("torso_pitch")


def test_card_operating_points_are_equilibria(models):
    from pidlab.linear.linearize import linearize

    for env_id, loaded in models.items():
        lin = linearize(loaded)
        assert lin.op.source.startswith("card:")
        assert lin.equilibrium_error < 1e-8, (env_id, lin.xdot0)


GOOD = """
schema = "pidlab.model-card/1"
env_id = "X-v0"
[operating_point]
qpos = [0.0]
qvel = [0.0]
ctrl = [0.0]
[[observation]]
name = "a_pos"
source = "qpos"
joint = "a"
[[termination]]
signal = "a_pos"
low = -1
high = 1
"""


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda s: s.replace('"pidlab.model-card/1"', '"pidlab.model-card/9"'), "schema"),
        (lambda s: s.replace('source = "qpos"', 'source = "xpos"'), "allowed: qpos, qvel, qfrc_constraint"),
        (lambda s: s.replace('joint = "a"', "joint = 3"), "joint: expected str"),
        (
            lambda s: s.replace("qvel = [0.0]", 'qvel = ["x"]'),
            "operating_point.qvel = 'x': expected a finite number",
        ),
        (
            lambda s: s.replace("qvel = [0.0]", "qvel = [nan]"),
            "operating_point.qvel = nan: expected a finite number",
        ),
        (
            lambda s: s.replace("qvel = [0.0]", "qvel = [true]"),
            "operating_point.qvel = True: expected a finite",
        ),
        (lambda s: s.replace("qvel = [0.0]", "qvel = 3"), "qvel: expected list, got 3"),
        (
            lambda s: s.replace("low = -1", "low = nan"),
            "termination[0].low = nan: expected a number (inf allowed",
        ),
        (
            lambda s: s.replace('joint = "a"', 'joint = "a"\nclip = [1.0]'),
            "clip: expected a list of 2 numbers",
        ),
        (
            lambda s: s.replace('joint = "a"', 'joint = "a"\nclip = [1.0, nan]'),
            "clip = nan: expected a finite number",
        ),
        (lambda s: s.replace('joint = "a"', 'joint = "a"\nclip = [1.0, -1.0]'), "must be below high"),
        (lambda s: s.replace('name = "a_pos"', 'name = "a.pos"'), "name = 'a.pos': expected a name"),
        (lambda s: s.replace('env_id = "X-v0"', 'env_id = "../../x"'), "env_id = '../../x': expected a name"),
        (
            lambda s: "termination = 3\n" + s.split("[[termination]]")[0],
            "termination: expected a list of tables",
        ),
        (lambda s: "terminate_on_nonfinite = 1\n" + s, "terminate_on_nonfinite = 1: expected true or false"),
        (
            lambda s: (
                s + '[tuning]\n[[tuning.loop]]\nname = "l"\nsignal = "a_pos"\nactuators = { m = nan }\n'
            ),
            "actuators.m = nan: expected a finite number",
        ),
        (lambda s: s + "[paper]\nwin_target = nan\n", "paper: missing field"),
        (lambda s: s.replace("low = -1", "low = 2"), "must be below high"),
        (
            lambda s: s.replace('name = "a_pos"', 'name = "a_pos"\ntransform = "tan"'),
            "allowed: identity, sin, cos",
        ),
        (lambda s: s.replace("high = 1", 'high = 1\ninterval = "half"'), "allowed: closed, open"),
        (  # a field of one table written in another is no silent default (pidlab reads only its own)
            lambda s: s.replace("[[termination]]", 'interval = "half"\n[[termination]]'),
            "observation[0]: unknown field(s) ['interval']",
        ),
        (lambda s: "colour = 1\n" + s, "card.toml: unknown field(s) ['colour']"),
        (lambda s: s.replace('env_id = "X-v0"', ""), "missing field 'env_id'"),
    ],
)
def test_malformed_cards_name_the_field(edit, message):
    import tomllib

    with pytest.raises(ModelCardError, match=re.escape(message)):
        parse_card(tomllib.loads(edit(GOOD)), "card.toml")


def test_card_that_names_a_missing_joint(models, tmp_path):
    import tomllib

    card = parse_card(tomllib.loads(GOOD), "card.toml")
    with pytest.raises(ModelCardError, match="no joint 'a' in the model; joints: slider, hinge"):
        card.check_against(models["InvertedPendulum-v5"].model, 2)
    bad = tmp_path / "bad.toml"
    bad.write_text("schema = [", encoding="utf-8")
    with pytest.raises(ModelCardError, match="not valid TOML"):
        load_card(bad)


@pytest.mark.parametrize(
    ("text", "parsed"),
    [
        ("hinge_pos", Signal("pos", "hinge")),
        ("hinge2_vel", Signal("vel", "hinge2")),
        ("foot_left_joint_pos", Signal("pos", "foot_left_joint")),  # the last "_" splits
        ("site:tip:z", Signal("site", "tip", 2)),
        ("site:a:b:y", Signal("site", "a:b", 1)),  # the last ":" splits
        ("hinge_acc", None),
        ("_pos", None),
        ("hinge", None),
        ("site:tip:w", None),
        ("site::x", None),
        ("", None),
    ],
)
def test_the_signal_syntax_by_hand(text, parsed):
    assert parse_signal(text) == parsed
