"""Pushes the coach alone recovers from (pidlab.region.recovery), starts on the floor
(pidlab.plant.ground) and the room preset on the contact-rich envs (pidlab.region.room_env).

Real MuJoCo and the coach's real law; the figures checked are mechanics (what a start is, what
is counted, determinism), not how good a coach is.
"""

from __future__ import annotations

import dataclasses
import json
import re

import mujoco
import numpy as np
import pytest

from pidlab.controller.spec import load_spec
from pidlab.errors import ModelCardError, PidlabError, RegionError
from pidlab.linear.linearize import linearize
from pidlab.plant.card import parse_card
from pidlab.plant.ground import clearance, ground_of, on_floor
from pidlab.region.recovery import (
    episode_starts,
    measure_recovery,
    perturbation_start,
    perturbations_of,
    reachable,
    survived,
)
from pidlab.region.simulate import Simulator
from tests.helpers import TUNING, cli_in_process
from tests.test_cards import GOOD

IP, WALKER, HOPPER = "InvertedPendulum-v5", "Walker2d-v5", "Hopper-v5"


def _spec(env: str, name: str = "pidlab-robust"):
    return load_spec(TUNING / f"{env}.{name}.toml")


# ---------------------------------------------------------------- the card's [[perturbation]] tables

PUSH = '[[perturbation]]\nname = "tilt"\nkind = "pose"\ndirection = { a = 1.0 }\nlimit = 0.5\nunit = "rad"\n'


def test_a_card_reads_its_perturbations() -> None:
    import tomllib

    card = parse_card(tomllib.loads(GOOD + PUSH), "card.toml")
    (pt,) = card.perturbation
    assert (pt.name, pt.kind, pt.direction, pt.limit, pt.unit) == ("tilt", "pose", (("a", 1.0),), 0.5, "rad")


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda s: s.replace('kind = "pose"', 'kind = "shove"'), "kind: 'shove'; allowed: pose, velocity"),
        (lambda s: s.replace("{ a = 1.0 }", "{ a = 0.0 }"), "direction: expected at least one joint"),
        (lambda s: s.replace("{ a = 1.0 }", "{ a = nan }"), "direction.a = nan: expected a finite number"),
        (lambda s: s.replace("limit = 0.5", "limit = 0"), "limit = 0: expected a finite number > 0"),
        (lambda s: s.replace("limit = 0.5\n", ""), "missing field 'limit'"),
        (lambda s: s + "colour = 1\n", "perturbation[0]: unknown field(s) ['colour']"),
        (lambda s: s + s, "perturbation[1].name: 'tilt' is repeated"),
    ],
)
def test_malformed_perturbations_name_the_field(edit, message) -> None:
    import tomllib

    with pytest.raises(ModelCardError, match=re.escape(message)):
        parse_card(tomllib.loads(GOOD + edit(PUSH)), "card.toml")


def test_a_perturbation_of_a_missing_joint_is_refused(models) -> None:
    import tomllib

    text = GOOD.replace('joint = "a"', 'joint = "hinge"').replace('"a_pos"', '"hinge_pos"') + PUSH.replace(
        "{ a = 1.0 }", "{ knee = 1.0 }"
    )
    card = parse_card(tomllib.loads(text), "card.toml")
    with pytest.raises(ModelCardError, match="perturbation 'tilt': no joint 'knee' in the model"):
        card.check_against(models[IP].model, 2)


# ---------------------------------------------------------------- starts on the floor


def test_only_a_robot_standing_on_a_floor_has_a_ground(models) -> None:
    for env in ("InvertedPendulum-v5", "InvertedDoublePendulum-v5"):
        card = models[env].require_card()
        assert ground_of(models[env].model, np.array(card.operating_point.qpos)) is None
    m = models[WALKER].model
    g = ground_of(m, np.array(models[WALKER].require_card().operating_point.qpos))
    assert g is not None
    assert g.height_qpos == int(m.jnt_qposadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, "rootz")])
    assert -0.01 < g.clearance < 0.0  # the soft contacts press in a little at the standing pose


def test_a_tilted_start_is_moved_onto_the_floor_and_nothing_else_moves(models) -> None:
    m = models[WALKER].model
    q0 = np.array(models[WALKER].require_card().operating_point.qpos)
    g = ground_of(m, q0)
    d = mujoco.MjData(m)
    d.qpos[:] = q0
    d.qpos[1] += 0.05  # raised and tilted: the feet hang above the floor
    d.qpos[2] += 0.3
    mujoco.mj_kinematics(m, d)
    assert abs(clearance(m, d, g.pairs) - g.clearance) > 0.01
    before = d.qpos.copy()
    shift = on_floor(m, d, g)
    mujoco.mj_kinematics(m, d)
    assert clearance(m, d, g.pairs) == pytest.approx(g.clearance, abs=1e-9)
    moved = np.flatnonzero(d.qpos != before)
    assert moved.tolist() == [g.height_qpos]
    assert d.qpos[g.height_qpos] - before[g.height_qpos] == pytest.approx(shift, abs=1e-12)


def test_a_grounded_start_at_the_operating_point_is_the_operating_point(models) -> None:
    loaded = models[HOPPER]
    sim = Simulator(_spec(HOPPER), loaded, linearize(loaded))
    sim.start(np.zeros(2 * loaded.model.nv), grounded=True)
    assert np.allclose(sim.d.qpos, sim.lin.op.qpos, atol=1e-9)


# ---------------------------------------------------------------- the measurement


def test_a_perturbation_start_is_its_direction_times_its_magnitude(models) -> None:
    m = models[WALKER].model
    tilt = next(p for p in models[WALKER].require_card().perturbation if p.name == "tilt")
    x = perturbation_start(tilt, m, 0.1)
    dof = {m.joint(j).name: int(m.jnt_dofadr[j]) for j in range(m.njnt)}
    expected = np.zeros(2 * m.nv)
    expected[[dof["rooty"], dof["thigh_joint"], dof["thigh_left_joint"]]] = [0.1, 0.1, 0.1]
    assert np.array_equal(x, expected)
    push = next(p for p in models[WALKER].require_card().perturbation if p.name == "push")
    assert np.flatnonzero(perturbation_start(push, m, -1.5)).tolist() == [m.nv + dof["rootx"]]


def test_a_start_past_the_termination_rule_is_held_for_no_step(models) -> None:
    loaded = models[IP]
    sim = Simulator(_spec(IP), loaded, linearize(loaded))
    tilt = next(p for p in loaded.require_card().perturbation if p.name == "tilt")
    assert survived(sim, perturbation_start(tilt, loaded.model, 0.25), 100) == 0  # |hinge| > 0.2 ends it
    assert survived(sim, perturbation_start(tilt, loaded.model, 0.0), 100) == 100


def test_the_measurement_counts_what_it_says_and_repeats_itself(models) -> None:
    loaded = models[IP]
    spec = _spec(IP, "pidlab-rescue")
    a = measure_recovery(spec, loaded, probes=5, episodes=12, horizon_s=1.0, seed=3)
    assert a == measure_recovery(spec, loaded, probes=5, episodes=12, horizon_s=1.0, seed=3)
    assert [r.name for r in a.reach] == [p.name for p in loaded.require_card().perturbation]
    for r in a.reach:  # a reach is one of the probed magnitudes
        for side in (r.negative, r.positive):
            assert 0.0 <= side <= r.limit and round(side / r.limit * 5, 9).is_integer()
    # the falls recounted by hand from the same starts
    sim = Simulator(spec, loaded, linearize(loaded))
    steps = round(1.0 / loaded.control_dt)
    starts = episode_starts(perturbations_of(loaded), loaded.model, 12, 3)
    assert a.falls == sum(survived(sim, x, steps) < steps for x in starts)
    assert a.falls_ci[0] <= a.falls_per_100 <= a.falls_ci[1]


def test_a_card_without_perturbations_is_refused_in_one_line(models) -> None:
    loaded = models[IP]
    bare = dataclasses.replace(loaded, card=dataclasses.replace(loaded.require_card(), perturbation=()))
    with pytest.raises(RegionError, match=r"no \[\[perturbation\]\] tables"):
        measure_recovery(_spec(IP), bare)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--episodes", "-1"], "--episodes -1: expected an integer in [0, 1000000]"),
        (["--probes", "0"], "--probes 0: expected an integer in [1, 1000]"),
        (["--horizon", "nan"], "--horizon nan: expected a finite number in (0, 600]"),
        (
            [str(TUNING / "Walker2d-v5.pidlab-robust.toml")],
            "coaches of InvertedPendulum-v5, Walker2d-v5; expected",
        ),
    ],
)
def test_recovery_cli_refuses_bad_input_in_one_line(args, message) -> None:
    code, err = cli_in_process("recovery", str(TUNING / "InvertedPendulum-v5.pidlab-robust.toml"), *args)
    assert code == 2 and message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_recovery_cli_prints_and_writes_the_figures(tmp_path) -> None:
    from typer.testing import CliRunner

    from pidlab.cli import app

    out_file = tmp_path / "recovery.json"
    result = CliRunner().invoke(app, [
        "recovery", str(TUNING / "InvertedPendulum-v5.pidlab-robust.toml"),
        str(TUNING / "InvertedPendulum-v5.pidlab-rescue.toml"),
        "--episodes", "4", "--probes", "3", "--horizon", "0.5", "--json", str(out_file),
    ])  # fmt: skip
    assert result.exit_code == 0, result.stderr
    out = result.stdout
    assert "pidlab-robust" in out and "pidlab-rescue" in out and "tilt (rad), reach" in out
    data = json.loads(out_file.read_text())
    assert [d["spec_name"] for d in data] == ["pidlab-robust", "pidlab-rescue"]
    assert all(d["episodes"] == 4 and d["falls_per_100"] == 25.0 * d["falls"] for d in data)


# ---------------------------------------------------------------- the room preset on the env


def test_room_on_the_env_keeps_the_template_and_repeats_itself(models) -> None:
    from pidlab.region.room_env import tune_room_on_env

    loaded = models[HOPPER]
    a = tune_room_on_env(loaded, candidates=2, refine=2, episodes=3)
    b = tune_room_on_env(loaded, candidates=2, refine=2, episodes=3)
    assert a.spec == b.spec
    template = loaded.require_card().tuning
    assert [lp.name for lp in a.spec.loops] == [lt.name for lt in template]
    for lp, lt in zip(a.spec.loops, template, strict=True):
        if lt.auto_weights:  # the spread loop: kp 1, one weight per actuator
            assert lp.kp == 1.0 and [n for n, _ in lp.actuators] == list(loaded.input_names)
        else:  # a joint loop opposes its joint's deviation (direct action, positive gear)
            assert lp.kp < 0 and lp.kd < 0 and lp.actuators == lt.actuators
    prov = a.spec.provenance
    assert prov["preset"] == "room" and prov["room_starts"] == 3 and prov["room_starts_seed"] == 1000
    assert 0.0 < prov["room_held_share"] <= 1.0 and a.evaluations == 2 + 2 * 2


def test_room_is_refused_where_the_coach_is_refined_on_the_env_with_nothing_to_search_on(models) -> None:
    from pidlab.region.room import tune_for_room

    loaded = models[HOPPER]
    bare = dataclasses.replace(loaded, card=dataclasses.replace(loaded.require_card(), perturbation=()))
    with pytest.raises(PidlabError, match=r"no \[\[perturbation\]\] tables to search its gains on"):
        tune_for_room(bare)


def test_scaled_starts_are_the_same_draws_scaled(models) -> None:
    m = models[WALKER].model
    perturbations = perturbations_of(models[WALKER])
    full = episode_starts(perturbations, m, 8, 5)
    half = episode_starts(perturbations, m, 8, 5, scale=0.5)
    assert all(np.allclose(0.5 * a, b) for a, b in zip(full, half, strict=True))
    assert sum(np.count_nonzero(x) > 0 for x in full) == 8  # every start is pushed


@pytest.mark.parametrize("env", ["Hopper-v5", "Walker2d-v5"])
def test_the_cards_tilt_turns_the_torso_and_leaves_the_legs_as_they_stand(env, models) -> None:
    """``rooty`` turns about +y and the hips about -y: the tilt's hips move with it, not against it."""
    loaded = models[env]
    m, d = loaded.model, mujoco.MjData(loaded.model)
    (tilt,) = [p for p in perturbations_of(loaded) if p.name == "tilt"]
    op = np.array(loaded.require_card().operating_point.qpos)

    def frames(dq: np.ndarray) -> dict[str, np.ndarray]:
        q = op.copy()
        mujoco.mj_integratePos(m, q, dq, 1.0)
        d.qpos[:] = q
        mujoco.mj_kinematics(m, d)
        return {name: d.xmat[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, name)].copy()
                for name in ("torso", "thigh")}  # fmt: skip

    still, tilted = frames(np.zeros(m.nv)), frames(perturbation_start(tilt, m, -0.1)[: m.nv])
    assert np.allclose(tilted["thigh"], still["thigh"], atol=1e-12)  # the leg as it stands
    assert not np.allclose(tilted["torso"], still["torso"], atol=1e-3)  # the torso tilted


def test_a_start_outside_a_joint_s_range_is_not_probed_nor_drawn(models) -> None:
    loaded = models["Walker2d-v5"]
    spec = load_spec(TUNING / "Walker2d-v5.pidlab-balance.toml")
    found = measure_recovery(spec, loaded, probes=4, episodes=40, seed=3)
    (tilt,) = [r for r in found.reach if r.name == "tilt"]
    # a forward tilt of the torso with the legs as they stand needs the hips past their stop at 0
    assert tilt.positive_range == 0.0 and tilt.positive == 0.0 and tilt.negative_range == tilt.limit
    sim = Simulator(spec, loaded, linearize(loaded))
    starts = episode_starts(perturbations_of(loaded), loaded.model, 40, 3, keep=lambda x: reachable(sim, x))
    assert all(reachable(sim, x) for x in starts)
    drawn = episode_starts(perturbations_of(loaded), loaded.model, 40, 3)
    assert not all(reachable(sim, x) for x in drawn)  # without the rule some would lie past a stop
