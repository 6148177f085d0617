"""Coach specs: exact round trips and validation of malformed files."""

from __future__ import annotations

from pathlib import Path

import pytest

from pidlab.controller.pid import Coach
from pidlab.controller.spec import dumps_spec, load_spec, loads_spec, save_spec
from pidlab.errors import SpecError

TUNING = Path(__file__).resolve().parents[1] / "tuning"
SHIPPED = sorted(TUNING.glob("*.toml"))


def test_every_env_has_shipped_specs():
    names = {p.name for p in SHIPPED}
    for env in ("InvertedPendulum-v5", "InvertedDoublePendulum-v5", "Hopper-v5", "Walker2d-v5"):
        for kind in ("paper", "pidlab-robust", "pidlab-weak"):
            assert f"{env}.{kind}.toml" in names


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_shipped_specs_round_trip_exactly(path, models):
    text = path.read_text(encoding="utf-8")
    spec = load_spec(path)
    assert dumps_spec(spec) == text  # save(load(file)) == file, byte for byte
    assert loads_spec(dumps_spec(spec)) == spec
    Coach(spec, models[spec.env_id])  # names check out against the env


def test_save_is_atomic_and_reloads(tmp_path):
    spec = load_spec(TUNING / "InvertedPendulum-v5.paper.toml")
    out = save_spec(spec, tmp_path / "sub" / "copy.toml")
    assert load_spec(out) == spec
    assert not list((tmp_path / "sub").glob(".*.tmp"))


BASE = (TUNING / "InvertedPendulum-v5.paper.toml").read_text(encoding="utf-8")


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        (
            'schema = "pidlab.coach-spec/1"',
            'schema = "pidlab.coach-spec/0"',
            "expected 'pidlab.coach-spec/1'",
        ),
        ("kp = 15.0", 'kp = "fifteen"', "loop 'pole'.kp: expected a number"),
        ("kp = 15.0", "kp = true", "loop 'pole'.kp: expected a number"),
        ("tf = 0.0", "tf = -0.01", "tf: -0.01 is negative"),
        ('anti_windup = "clamping"', 'anti_windup = "magic"', "allowed: none, clamping, back-calculation"),
        (
            'anti_windup = "clamping"',
            'anti_windup = "back-calculation"',
            "needs a tracking time constant > 0 s",
        ),
        ('action = "direct"', 'action = "sideways"', "allowed: reverse, direct"),
        ("kd = 2.25", "kd = 2.25\ngain = 3", "unknown field(s) ['gain']"),
        ('env_id = "InvertedPendulum-v5"', 'env_id = ""', "env_id: expected a non-empty string"),
        ("[loop.actuators]\nslide = 1.0", "[loop.actuators]", "give either actuators"),
        ("[loop.actuators]\nslide = 1.0", 'feeds = "nowhere"', "no loop 'nowhere'"),
        ("[loop.actuators]\nslide = 1.0", 'feeds = "pole"', "feeds itself"),
        ("output_limits = [\n    -inf,\n    inf,\n]", "output_limits = [1.0, -1.0]", "must be below high"),
        ("output_limits = [\n    -inf,\n    inf,\n]", "output_limits = [1.0]", "expected [low, high]"),
        ('name = "pole"', 'name = "pole"\nname = "x"', "not valid TOML"),
        ("[[loop]]", "[loop]", "expected at least one [[loop]]"),
    ],
)
def test_malformed_spec_names_the_field(old, new, message):
    assert old in BASE
    with pytest.raises(SpecError, match=__import__("re").escape(message)):
        loads_spec(BASE.replace(old, new, 1))


def test_an_analysis_table_is_refused_not_dropped():
    """A table the spec would not write back is refused, so load -> save loses nothing."""
    with pytest.raises(SpecError, match=r"unknown field\(s\) \['analysis'\]; allowed: .*'bounds'"):
        loads_spec(BASE + "\n[analysis]\nbandwidth = 1.0\n")


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        (
            'signal = "hinge_pos"',
            'signal = "pole_angle"',
            "'pole_angle' is not an observation variable of InvertedPendulum-v5; valid names: slider_pos, hinge_pos",
        ),
        (
            'rate_signal = "hinge_vel"',
            'rate_signal = "hinge_rate"',
            "rate_signal: 'hinge_rate' is not an observation",
        ),
        (
            "[loop.actuators]\nslide = 1.0",
            "[loop.actuators]\nmotor = 1.0",
            "no actuator 'motor' in InvertedPendulum-v5; actuators: slide",
        ),
        ('description = "', '[offset]\nslide = 5.0\n\n[x]\ndescription = "', "unknown field"),
    ],
)
def test_names_checked_against_the_env(old, new, message, models):
    with pytest.raises(SpecError, match=__import__("re").escape(message)):
        Coach(loads_spec(BASE.replace(old, new, 1)), models["InvertedPendulum-v5"])


def test_offset_outside_ctrlrange(models):
    text = BASE.replace("[[loop]]", "[offset]\nslide = 5.0\n\n[[loop]]", 1)
    with pytest.raises(
        SpecError, match=r"offset.slide = 5.0 is outside the actuator's ctrlrange \[-3.0, 3.0\]"
    ):
        Coach(loads_spec(text), models["InvertedPendulum-v5"])


def test_spec_for_another_env(models):
    with pytest.raises(SpecError, match="the spec is for InvertedPendulum-v5, not for Hopper-v5"):
        Coach(loads_spec(BASE), models["Hopper-v5"])


def test_cascade_cycle():
    text = BASE.replace("[loop.actuators]\nslide = 1.0", 'feeds = "b"') + (
        '\n[[loop]]\nname = "b"\nsignal = "slider_pos"\nfeeds = "pole"\n'
    )
    with pytest.raises(SpecError, match="cascade cycle"):
        loads_spec(text)
