"""The exact rescue test (pidlab.region.oracle): its answers, and the shield made of it.

Real MuJoCo with the shipped coaches; the numbers asked are the ones measured on them (a state
one step of the full action away from rest is already beyond the InvertedDoublePendulum coach).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pidlab.controller.spec import load_spec
from pidlab.errors import RegionError
from pidlab.plant.model import load_model
from pidlab.region.oracle import RescueOracle, reset_states, shield_episode, shield_floor
from pidlab.region.simulate import Simulator
from tests.helpers import ROOT

IDP_SPEC = ROOT / "tuning" / "InvertedDoublePendulum-v5.pidlab-rescue-full.toml"
IP_SPEC = ROOT / "tuning" / "InvertedPendulum-v5.pidlab-rescue-edge.toml"


@pytest.fixture(scope="module")
def idp() -> tuple:
    spec = load_spec(IDP_SPEC)
    return spec, load_model(spec.env_id)


def test_the_oracle_rescues_rest_and_a_small_push_but_not_a_full_one(idp: tuple) -> None:
    spec, loaded = idp
    oracle = RescueOracle(spec, loaded)
    rest = np.zeros(2 * loaded.model.nv)
    assert oracle.rescues(rest)
    assert oracle.rescues(rest, np.array([0.2]))
    assert not oracle.rescues(rest, np.array([1.0]))
    assert not oracle.rescues(rest, np.array([-1.0]))
    assert oracle.questions == 4


def test_under_the_oracle_an_agent_that_always_pushes_never_falls(idp: tuple) -> None:
    """Every push that runs leads where the coach rescues, and the coach acts from such states only."""
    spec, loaded = idp
    oracle = RescueOracle(spec, loaded)
    run = Simulator(spec, loaded, oracle.lin)
    (start,), limit, _ = reset_states(spec.env_id, 1, 3)
    assert limit == 1000  # the env's own time limit
    episode = shield_episode(oracle, run, start, 120, lambda: np.array([1.0]))
    assert episode.start_rescued and not episode.fell and episode.steps == 120
    assert 60 < episode.coach_steps <= 120  # most pushes are vetoed
    assert oracle.questions == 121  # the start, then one question per step


def test_the_shield_floor_is_deterministic_and_its_accounts_add_up() -> None:
    spec = load_spec(IP_SPEC)
    loaded = load_model(spec.env_id)
    one = shield_floor(spec, loaded, episodes=2, seed=5, max_steps=80)
    assert one == shield_floor(spec, loaded, episodes=2, seed=5, max_steps=80)
    assert [e.steps for e in one.episodes] == [80, 80] and one.falls == 0
    assert all(e.start_rescued and 0 < e.coach_steps < e.steps for e in one.episodes)
    assert one.coach_share == pytest.approx(one.coach_steps / 160)
    other = shield_floor(spec, loaded, episodes=2, seed=6, max_steps=80)
    assert other.episodes != one.episodes
    assert dataclasses.asdict(one)["episodes"][0]["steps"] == 80


@pytest.mark.parametrize(
    ("settings", "says"),
    [
        ({"episodes": 0}, "episodes = 0: expected an integer in [1, 100000]"),
        ({"std": 0.0}, "std = 0.0: expected a finite number in (0, 100]"),
        ({"std": float("nan")}, "std = nan"),
        ({"seed": -1}, "seed = -1"),
        ({"into": "floor"}, "into='floor': expected one of core, box"),
        ({"horizon_s": 0.0}, "horizon_s = 0"),
        ({"max_steps": 0}, "max_steps = 0: expected an integer in [1, 10000000]"),
    ],
)
def test_a_setting_out_of_range_is_one_region_error(settings: dict, says: str) -> None:
    spec = load_spec(IP_SPEC)
    with pytest.raises(RegionError) as caught:
        shield_floor(spec, load_model(spec.env_id), **{"episodes": 1, "max_steps": 5, **settings})
    assert says in str(caught.value) and "\n" not in str(caught.value)


def test_the_published_shield_floor_table_is_its_json_files() -> None:
    """docs/rescue.md's table is what benchmarks/shield_floor.py makes of its JSON and the published runs."""
    import subprocess
    import sys

    done = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "shield_floor.py"), "--check"],
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert "matches" in done.stdout


def test_a_coach_not_measured_yet_is_left_out_of_the_shield_floor_table(monkeypatch) -> None:
    """A row added to the script before its env is measured again: no row for it, the others kept."""
    sys_path = str(ROOT / "benchmarks")
    monkeypatch.syspath_prepend(sys_path)
    import shield_floor

    before = shield_floor.table()
    walker = shield_floor.COACHES["Walker2d-v5"]
    extra = shield_floor.Row(shield_floor.Coach("a coach no JSON holds yet", "tuning/Walker2d-v5.pidlab-robust.toml"))
    monkeypatch.setitem(shield_floor.COACHES, "Walker2d-v5", (*walker, extra))
    assert shield_floor.table() == before
    assert "a coach no JSON holds yet" not in before and before.count("| Walker2d-v5 |") == len(walker)


@pytest.mark.parametrize(
    ("x", "ctrl", "says"),
    [
        (np.zeros(3), None, "x_plant: expected 6 finite numbers, got shape (3,)"),
        (
            np.full(6, np.nan),
            None,
            "x_plant: expected 6 finite numbers, got a non-finite value",
        ),
        (
            np.zeros(6),
            np.array([np.inf]),
            "ctrl: expected 1 finite number, got a non-finite value",
        ),
        (np.zeros(6), np.zeros(2), "ctrl: expected 1 finite number, got shape (2,)"),
        ("rest", None, "x_plant: expected 6 finite numbers, got str"),
    ],
)
def test_a_bad_question_is_one_region_error(idp: tuple, x: object, ctrl: object, says: str) -> None:
    oracle = RescueOracle(*idp)
    with pytest.raises(RegionError) as caught:
        oracle.rescues(x, ctrl)  # type: ignore[arg-type]
    assert says in str(caught.value) and "\n" not in str(caught.value)
    assert oracle.questions == 0


def test_a_spec_of_an_env_gymnasium_does_not_know_is_one_region_error() -> None:
    spec = load_spec(IP_SPEC)
    loaded = load_model(spec.env_id)
    with pytest.raises(RegionError, match=r"^Nope-v5: no Gymnasium env to draw reset states from \("):
        shield_floor(dataclasses.replace(spec, env_id="Nope-v5"), loaded, episodes=1, max_steps=5)
