"""The balance preset (pidlab.controller.balance): the card's [balance] table, the posture, the law.

Real MuJoCo: the posture is checked by its kinematics, the coach's law against ``clip(u0 - K (y -
y*))`` computed by hand from the design, and the shipped specs against what the preset builds now.
How often the coach falls from perturbed starts is a benchmark (docs/coach.md), not a test.
"""

from __future__ import annotations

import dataclasses
import re

import mujoco
import numpy as np
import pytest
import tomllib

from pidlab.controller.analysis import analyze_coach
from pidlab.controller.balance import (
    FLAT_TOLERANCE,
    _Geometry,
    balance_gain,
    balanced_posture,
    design_linearization,
    design_observation,
    tune_balance,
)
from pidlab.controller.pid import Coach
from pidlab.controller.spec import load_spec
from pidlab.errors import ModelCardError, PidlabError
from pidlab.linear.linearize import linearize
from pidlab.plant.card import parse_card
from pidlab.plant.operating_point import resolve_operating_point
from pidlab.region.recovery import survived
from pidlab.region.simulate import Simulator, horizon_steps
from tests.helpers import TUNING, cli_in_process
from tests.test_cards import GOOD

LEGGED = ("Hopper-v5", "Walker2d-v5")

BALANCE = (
    '[balance]\nfeet = ["foot"]\nbend = { knee = -0.1 }\nhips = ["hip"]\nankles = ["ankle"]\n'
    'height = "rootz"\npitch = "rooty"\n'
)


def test_a_card_reads_its_balance_table() -> None:
    card = parse_card(tomllib.loads(GOOD + BALANCE), "card.toml")
    b = card.balance
    assert b is not None
    assert (b.feet, b.bend, b.hips, b.ankles, b.height, b.pitch) == (
        ("foot",),
        (("knee", -0.1),),
        ("hip",),
        ("ankle",),
        "rootz",
        "rooty",
    )
    assert b.joints() == ("knee", "hip", "ankle", "rootz", "rooty")
    assert parse_card(tomllib.loads(GOOD), "card.toml").balance is None


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (
            lambda s: s.replace('feet = ["foot"]', "feet = []"),
            "balance.feet: expected a non-empty list of names",
        ),
        (lambda s: s.replace('hips = ["hip"]', 'hips = "hip"'), "balance.hips: expected a non-empty list"),
        (
            lambda s: s.replace("knee = -0.1", "knee = 9.0"),
            "balance.bend.knee = 9.0: expected a finite number",
        ),
        (lambda s: s.replace('pitch = "rooty"\n', ""), "balance: missing field 'pitch'"),
        (lambda s: s + "colour = 1\n", "balance: unknown field(s) ['colour']"),
    ],
)
def test_a_malformed_balance_table_names_the_field(edit, message) -> None:
    with pytest.raises(ModelCardError, match=re.escape(message)):
        parse_card(tomllib.loads(GOOD + edit(BALANCE)), "card.toml")


@pytest.mark.parametrize("env", LEGGED)
def test_the_posture_stands_flat_with_the_centre_of_mass_over_the_feet(env, models) -> None:
    loaded = models[env]
    card = loaded.require_card()
    posture = balanced_posture(loaded)
    m = loaded.model
    for joint, angle in card.balance.bend:
        assert posture.qpos[m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, joint)]] == angle
    for joint in card.balance.hips + card.balance.ankles:  # off the range limits the reset pose sits on
        jid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, joint)
        lo, hi = m.jnt_range[jid]
        assert lo < posture.qpos[m.jnt_qposadr[jid]] < hi
    before = posture.qpos.copy()
    before[[2]] = card.operating_point.qpos[2]  # the solved pose, before the settle tilted the base
    slope, offset = _Geometry(loaded, card.balance).residual(before)
    assert abs(offset) < 0.01 and abs(slope) < 0.02
    assert abs(posture.com_offset) < FLAT_TOLERANCE * 10  # settled: the floor carries it over mid-foot
    assert np.all(np.abs(posture.ctrl) < 1.0)  # held without saturating


@pytest.mark.parametrize("env", LEGGED)
def test_the_coach_law_is_the_full_state_feedback_of_the_design(env, models) -> None:
    loaded = models[env]
    posture = balanced_posture(loaded)
    op = resolve_operating_point(loaded, qpos=posture.qpos, qvel=np.zeros(loaded.model.nv), ctrl=posture.ctrl)
    lin = linearize(loaded, op, eps=1e-4)
    K = balance_gain(loaded, lin, posture)
    spec = tune_balance(loaded).spec
    card = loaded.require_card()
    y_star = np.array([lp.setpoint for lp in spec.loops])
    assert [lp.signal for lp in spec.loops] == list(card.observation_names)
    rng = np.random.default_rng(0)
    for _ in range(20):
        y = y_star + rng.normal(0.0, 0.05, len(y_star))
        coach = Coach(spec, loaded)
        assert np.allclose(coach.act(y), np.clip(posture.ctrl - K @ (y - y_star), -1.0, 1.0), atol=1e-12)
    A, B = np.asarray(lin.sysd.A), np.asarray(lin.sysd.B)
    rows = [list(lin.sysd.state_labels).index(f"{v.joint}_{'pos' if v.source == 'qpos' else 'vel'}")
            for v in card.observation]  # fmt: skip
    assert np.max(np.abs(np.linalg.eigvals(A[np.ix_(rows, rows)] - B[rows] @ K))) < 1.0


@pytest.mark.parametrize("env", LEGGED)
def test_the_shipped_balance_specs_are_what_the_preset_builds(env, models) -> None:
    shipped = load_spec(TUNING / f"{env}.pidlab-balance.toml")
    built = tune_balance(models[env]).spec
    assert dict(shipped.offset) == pytest.approx(dict(built.offset), abs=1e-9)
    for a, b in zip(shipped.loops, built.loops, strict=True):
        assert (a.signal, a.action, a.kp, a.kd) == (b.signal, b.action, b.kp, b.kd)
        assert a.setpoint == pytest.approx(b.setpoint, abs=1e-9)
        assert dict(a.actuators) == pytest.approx(dict(b.actuators), rel=1e-6, abs=1e-9)


@pytest.mark.parametrize("env", LEGGED)
def test_the_coach_holds_the_robot_standing_on_the_floor(env, models) -> None:
    loaded = models[env]
    spec = load_spec(TUNING / f"{env}.pidlab-balance.toml")
    sim = Simulator(spec, loaded, linearize(loaded))
    steps = horizon_steps(5.0, loaded.control_dt)
    assert survived(sim, np.zeros(2 * loaded.model.nv), steps) == steps


def test_a_card_without_a_balance_table_is_refused(models) -> None:
    with pytest.raises(
        PidlabError, match=r"preset balance: the model card of InvertedPendulum-v5 has no \[balance\]"
    ):
        tune_balance(models["InvertedPendulum-v5"])


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--bandwidth", "3"], "--bandwidth: --preset balance is a full-state LQR design about a posture"),
        (["--workers", "2"], "--workers: --preset balance runs no simulations in parallel"),
    ],
)
def test_balance_options_it_would_ignore_are_refused(args, message) -> None:
    code, err = cli_in_process(
        "tune", "Walker2d-v5", "--auto", "--preset", "balance", *args, "-o", "/proc/no/w.toml"
    )
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1


def test_a_bend_outside_the_joint_s_range_is_refused_with_the_card(models) -> None:
    import dataclasses

    loaded = models["Walker2d-v5"]
    card = loaded.require_card()
    bent = dataclasses.replace(card.balance, bend=(("leg_joint", 0.5), ("leg_left_joint", -0.15)))
    with pytest.raises(
        ModelCardError, match=r"balance.bend.leg_joint = 0.5: outside the joint's range \[-2.618, 0\]"
    ):
        dataclasses.replace(card, balance=bent).check_against(loaded.model, loaded.frame_skip)


def test_a_posture_that_needs_a_joint_outside_its_range_is_refused(models) -> None:
    import dataclasses

    loaded = models["Walker2d-v5"]
    card = loaded.require_card()
    # knees bent 1.5 rad: flat feet under the centre of mass would need the ankles past 0.785 rad
    deep = dataclasses.replace(card.balance, bend=(("leg_joint", -1.5), ("leg_left_joint", -1.5)))
    other = dataclasses.replace(loaded, card=dataclasses.replace(card, balance=deep))
    with pytest.raises(PidlabError, match="preset balance: the posture of .* needs .* outside its range"):
        balanced_posture(other)


@pytest.mark.parametrize("env", LEGGED)
def test_the_analysis_of_a_balance_coach_is_at_its_posture(env, models) -> None:
    """``pidlab analyze`` linearizes a balance coach where it was designed, not at the reset pose."""
    loaded = models[env]
    spec = load_spec(TUNING / f"{env}.pidlab-balance.toml")
    lin = design_linearization(spec, loaded)
    assert lin is not None and lin.eps == 1e-4
    assert lin.op.qpos == pytest.approx(spec.provenance["balance_posture_qpos"], abs=1e-12)
    assert lin.op.ctrl == pytest.approx([dict(spec.offset)[a] for a in loaded.input_names], abs=1e-12)
    # the same closed loop the design reported: stable at the posture
    analysis = analyze_coach(Coach(spec, loaded), loaded, lin)
    assert analysis.stable
    radius = max(abs(p.value) for p in analysis.discrete.poles)
    assert radius == pytest.approx(spec.provenance["balance_lqr_spectral_radius"], abs=1e-3)
    from typer.testing import CliRunner

    from pidlab.cli import app

    result = CliRunner().invoke(
        app, ["analyze", str(TUNING / f"{env}.pidlab-balance.toml"), "--episodes", "0"]
    )
    out = result.stdout
    assert (
        result.exit_code == 0 and "plant linearized at the balance posture the coach was designed at" in out
    )
    assert " nan " not in out  # an undefined crossover is shown as "-"


def test_a_coach_of_another_preset_is_analysed_at_the_card_s_point(models) -> None:
    spec = load_spec(TUNING / "Walker2d-v5.pidlab-room.toml")
    assert design_linearization(spec, models["Walker2d-v5"]) is None


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"balance_linearize_eps": "x"}, "balance_linearize_eps 'x': expected a step in (0, 1)"),
        ({"balance_posture_qpos": [0.0, 1.0]}, "its recorded posture (provenance balance_posture_qpos): qpos has 2"),
    ],
)
def test_a_damaged_balance_provenance_is_refused_in_one_line(models, change, message) -> None:
    spec = load_spec(TUNING / "Walker2d-v5.pidlab-balance.toml")
    damaged = dataclasses.replace(spec, provenance={**spec.provenance, **change})
    with pytest.raises(PidlabError, match=re.escape(message)):
        design_linearization(damaged, models["Walker2d-v5"])
    no_u0 = dataclasses.replace(spec, offset=spec.offset[1:])
    with pytest.raises(PidlabError, match="offset names every actuator"):
        design_linearization(no_u0, models["Walker2d-v5"])


def test_a_classifier_region_of_a_balance_coach_is_anchored_at_its_posture(models) -> None:
    """The region must hold, and hands back toward, the posture the coach regulates to."""
    from pidlab.region.classifier import _anchor

    loaded = models["Walker2d-v5"]
    spec = load_spec(TUNING / "Walker2d-v5.pidlab-balance.toml")
    names = ("rooty_pos", "leg_joint_pos", "rooty_vel")
    setpoints = {lp.signal: lp.setpoint for lp in spec.loops}
    y = design_observation(spec, loaded, names)
    assert y == pytest.approx([setpoints[v] for v in names], abs=1e-12)  # the law's own setpoints
    box = ((-1.0, -2.0, -2.0), (1.0, 0.0, 2.0))
    assert _anchor(spec, loaded, names, box) == pytest.approx(tuple(y))
    assert _anchor(load_spec(TUNING / "Walker2d-v5.pidlab-room.toml"), loaded, names, box) is None
    with pytest.raises(PidlabError, match=r"the posture the coach regulates to lies outside the domain \(leg_joint_pos"):
        _anchor(spec, loaded, names, ((-1.0, -0.1, -2.0), (1.0, 0.0, 2.0)))
