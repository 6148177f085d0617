"""Rescue regions: the lookup grid and its TOML form, membership, the estimate in MuJoCo, the room preset.

The estimates run on InvertedPendulum-v5 with small grids and draws: what they check is the
mechanics (validated states really are rescued, the same result on any number of workers, the
accounts of the coverage), not the size of a full-budget region.
"""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pytest

from pidlab.controller.spec import load_spec, loads_spec
from pidlab.errors import CoachingError, RegionError, SpecError
from pidlab.lookup import LookupGrid, parse_lookup
from pidlab.plant.model import load_model
from pidlab.region.rescue import (
    RescueSettings,
    _core,
    _rescued,
    estimate_rescue,
    rescued_fraction,
    with_rescue,
)
from pidlab.region.simulate import Simulator
from pidlab.region.takeover import GridRegion, load_region, region_from_bounds
from tests.helpers import TUNING, cli_in_process

IP = "InvertedPendulum-v5"
NAMES = ("slider_pos", "hinge_pos", "slider_vel", "hinge_vel")


def _grid(table: list[list[int]], guard: dict[str, tuple[float, float]] | None = None) -> LookupGrid:
    t = np.array(table, dtype=bool)
    return LookupGrid(("hinge_pos", "hinge_vel"), (-0.2, -2.0), (0.2, 2.0), t.shape, t, guard or {})


def test_lookup_grid_round_trips_through_its_toml_table() -> None:
    g = _grid([[0, 1, 0], [1, 1, 1], [0, 1, 0], [0, 0, 1]], {"slider_pos": (-0.1, 0.1)})
    back = parse_lookup(g.to_table())
    assert back == g
    assert np.array_equal(back.table, g.table)
    assert back.guard == {"slider_pos": (-0.1, 0.1)}
    assert g.to_table()["rows"] == ["010", "111", "010", "001"]


def test_depth_counts_cells_to_the_nearest_unmarked_cell_or_edge() -> None:
    g = _grid([[1, 1, 1, 1, 1]] * 5)
    assert g.depth()[2, 2] == 3  # the centre of a full 5 x 5 grid is three cells from its edge
    assert g.depth()[0, 0] == 1
    assert _grid([[0, 0], [0, 0]]).depth().max() == 0


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("rows", ["01", "1"], "strings of"),
        ("rows", ["012", "111", "000", "000"], "characters 0 or 1"),
        ("cells", [4, 0], "whole numbers"),
        ("trigger", "sometimes", "expected one of reactive, predictive"),
        ("action_fraction", 1.5, r"in \[0, 1\]"),
        ("lower", [0.3, -2.0], "lower < upper"),
        ("guard", {"hinge_pos": [-1, 1]}, "cannot be a guard variable"),
        ("colour", "green", "unknown field"),
    ],
)
def test_a_damaged_rescue_table_is_one_spec_error(field: str, value: object, message: str) -> None:
    t = _grid([[0, 1, 0], [1, 1, 1], [0, 1, 0], [0, 0, 1]]).to_table()
    t[field] = value
    with pytest.raises(SpecError, match=message):
        parse_lookup(t)


def test_grid_membership_agrees_with_the_cell_lookup_and_the_guard() -> None:
    rng = np.random.default_rng(3)
    g = _grid(rng.random((7, 9)) < 0.5, {"slider_pos": (-0.1, 0.1)})
    region = GridRegion(g, NAMES)
    obs = np.column_stack(
        [
            rng.uniform(-0.15, 0.15, 4000),
            rng.uniform(-0.25, 0.25, 4000),
            np.zeros(4000),
            rng.uniform(-2.5, 2.5, 4000),
        ]
    )
    obs[:5, 1:4:2] = [[-0.2, -2.0], [0.2, 2.0], [0.2, -2.0], [0.0, 0.0], [-0.2, 2.0]]  # the grid's corners
    cells = g.cell_of(obs[:, [1, 3]])
    in_grid = np.array([c[0] >= 0 and bool(g.table[tuple(c)]) for c in cells])
    expected = in_grid & (np.abs(obs[:, 0]) <= 0.1)
    assert [region.contains(o) for o in obs] == list(expected)
    assert expected.any() and not expected.all()


def test_inner_keeps_only_the_deep_cells() -> None:
    region = GridRegion(_grid([[1] * 9] * 9), NAMES)
    assert region.max_depth == 5
    centre, edge = np.array([0, 0.0, 0, 0.0]), np.array([0, -0.19, 0, 0.0])
    inner = region.inner(0.5)
    assert region.contains(edge) and not inner.contains(edge) and inner.contains(centre)
    with pytest.raises(CoachingError, match=r"\(0, 1\]"):
        region.inner(0.0)


def test_inner_always_holds_the_operating_point_s_cell() -> None:
    # a 9 x 9 grid, full except a hole next to the centre: the centre cell is 1 deep, the corners'
    # blocks 2 or more; asking for the deep half must not leave out the operating point
    table = np.ones((9, 9), dtype=int)
    table[3, 3] = 0
    region = GridRegion(_grid(table.tolist()), NAMES)
    centre = np.array([0, 0.0, 0, 0.0])
    assert region.centre_depth == 1 and region.max_depth >= 3
    for fraction in (0.25, 0.5, 1.0):
        assert region.inner(fraction).contains(centre)
    # the cap: the centre is only 1 deep, so the hand-back region is the whole region
    assert region.inner(0.5).contains(np.array([0, -0.19, 0, 0.0]))


def test_load_region_gives_the_spec_s_takeover_region() -> None:
    path = TUNING / f"{IP}.pidlab-robust.toml"
    box = load_region(path)
    assert box.kind == "box"
    spec = load_spec(path)
    grid = _grid([[1] * 4] * 4)
    with_grid = dataclasses.replace(spec, bounds={**spec.bounds, "rescue": grid.to_table()})
    assert load_region(with_grid).kind == "rescue"  # a rescue region is the takeover one unless told
    told = dataclasses.replace(with_grid, bounds={**with_grid.bounds, "takeover": "box"})
    assert load_region(told).kind == "box"
    assert load_region(told, "ellipsoid").contains(np.array([0, -0.0017, 0, 0]))
    with pytest.raises(CoachingError, match=r"no \[bounds.rescue\]"):
        load_region(spec, "rescue")


def test_a_spec_naming_a_takeover_region_it_lacks_is_refused() -> None:
    text = (
        (TUNING / f"{IP}.pidlab-robust.toml")
        .read_text()
        .replace("[bounds]\n", '[bounds]\ntakeover = "rescue"\n', 1)
    )
    with pytest.raises(SpecError, match=r"takeover: 'rescue', but the table has no \[bounds.rescue\]"):
        loads_spec(text)


def _small(trigger: str = "predictive", fraction: float | None = None, **kw: object) -> RescueSettings:
    base = RescueSettings(
        ("hinge_pos", "hinge_vel"), (0.2, 2.5), (8, 10), {"slider_pos": 0.05}, trigger, fraction,
        probes=1, horizon_s=3.0, validation=150, coverage=150, seed=4,
    )  # fmt: skip
    return dataclasses.replace(base, **kw)


ROOM = TUNING / f"{IP}.pidlab-rescue.toml"
"""The shipped room coach: its cart loop brings the cart back into the guard box (the robust one's does not)."""


@pytest.fixture(scope="module")
def ip_region() -> tuple[object, object]:
    spec = load_spec(ROOM)
    return spec, estimate_rescue(spec, load_model(IP), _small(), workers=1)


def test_states_drawn_inside_the_region_are_rescued_in_a_fresh_simulation(ip_region: tuple) -> None:
    spec, r = ip_region
    loaded = load_model(IP)
    region = GridRegion(r.grid, NAMES)
    sim = Simulator(spec, loaded, _linearization(spec, loaded))
    rng = np.random.default_rng(99)
    checked = 0
    core = _core(spec, loaded.require_card())
    while checked < 20:
        x = np.zeros(4)
        x[[0, 1, 3]] = rng.uniform([-0.05, -0.2, -2.5], [0.05, 0.2, 2.5])
        obs = sim.start(x)
        if not region.contains(obs):
            continue
        ok, _ = _rescued(sim, (x, None), 75, core)
        assert ok, f"a state in the region was not rescued: {obs}"
        checked += 1
    assert r.validation == (150, 0)
    assert r.grid.table.sum() > 0


def _linearization(spec: object, loaded: object) -> object:
    from pidlab.controller.analysis import analyze_coach
    from pidlab.controller.pid import Coach

    return analyze_coach(Coach(spec, loaded), loaded).linearization


def test_coverage_accounts_add_up(ip_region: tuple) -> None:
    _, r = ip_region
    c = r.coverage
    assert c.samples == 150 and 0 < c.rescuable <= c.samples
    assert set(c.contained) == {"rescue", "core", "takeover ellipsoid", "takeover box"}
    for name, n in c.contained.items():
        assert 0 <= n <= c.rescuable
        assert 0.0 <= c.volume[name] <= 1.0
    assert r.provenance["coverage_rescue"] == pytest.approx(c.fraction("rescue"))
    assert r.provenance["validation_failures"] == 0


def test_the_estimate_is_the_same_on_two_workers(ip_region: tuple) -> None:
    spec, r = ip_region
    again = estimate_rescue(spec, load_model(IP), _small(), workers=2)
    assert np.array_equal(again.grid.table, r.grid.table)
    assert again.coverage == r.coverage


def test_a_reactive_region_has_room_for_the_agent_step_it_records() -> None:
    spec = load_spec(ROOM)
    r = estimate_rescue(spec, load_model(IP), _small("reactive", 0.1), workers=2)
    assert r.grid.trigger == "reactive" and r.grid.action_fraction == pytest.approx(0.1)
    assert r.settings.action_fraction == pytest.approx(0.1)
    assert not r.provenance["fraction_chosen"]
    # the predictive region holds the reactive one's states: no agent step to absorb
    p = estimate_rescue(spec, load_model(IP), _small(), workers=2)
    assert r.grid.table.sum() <= p.grid.table.sum()


def test_written_into_the_spec_it_becomes_the_takeover_region(ip_region: tuple, tmp_path: Path) -> None:
    spec, r = ip_region
    new = with_rescue(spec, r)
    text_spec = loads_spec(__import__("pidlab.controller.spec", fromlist=["dumps_spec"]).dumps_spec(new))
    region = region_from_bounds(text_spec.bounds, NAMES)
    assert region.kind == "rescue"
    assert text_spec.bounds["takeover"] == "rescue"
    assert text_spec.bounds["rescue"]["provenance"]["validation_samples"] == 150
    assert "box" in text_spec.bounds and "ellipsoid" in text_spec.bounds  # the certified core stays


def test_rescued_fraction_scores_every_coach_on_the_same_states() -> None:
    spec = load_spec(ROOM)
    loaded = load_model(IP)
    a = rescued_fraction(spec, loaded, _small(), 40, workers=1)
    b = rescued_fraction(spec, loaded, _small(), 40, workers=2)
    assert a == b and 0.0 < a < 1.0


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--trigger", "sometimes"], "--trigger 'sometimes': expected predictive or reactive"),
        (["--trigger", "reactive", "--fraction", "1.5"], "--fraction 1.5: expected a fraction"),
        (["--trigger", "reactive", "--fraction", "0"], "--fraction 0.0: expected a fraction"),
        (["--fraction", "0.5"], "the predictive trigger vets the agent's action itself"),
        (["--validation", "0"], "validation"),
    ],
)
def test_bad_rescue_options_are_one_line_and_exit_2(args: list[str], message: str, tmp_path: Path) -> None:
    spec = tmp_path / "s.toml"
    shutil.copy(TUNING / f"{IP}.pidlab-robust.toml", spec)
    before = spec.read_bytes()
    code, err = cli_in_process("rescue", str(spec), "--write", *args)
    assert code == 2
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("pidlab: error:") and message in lines[0]
    assert spec.read_bytes() == before


def test_rescue_settings_out_of_range_raise_region_error() -> None:
    spec = load_spec(ROOM)
    with pytest.raises(RegionError, match="cells"):
        estimate_rescue(spec, load_model(IP), _small(cells=(1, 10)))
    idp = load_spec(TUNING / "InvertedDoublePendulum-v5.pidlab-robust.toml")
    with pytest.raises(RegionError, match="joint's position, its sine or its velocity"):
        estimate_rescue(idp, load_model(idp.env_id), _small(variables=("hinge_cos", "hinge_vel"), guard={}))


def test_the_rescue_page_table_is_the_shipped_specs() -> None:
    import subprocess
    import sys

    from tests.helpers import ROOT

    done = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "rescue_table.py"), "--check"],
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stderr


@pytest.mark.parametrize(
    "env", ["InvertedPendulum-v5", "InvertedDoublePendulum-v5", "Hopper-v5", "Walker2d-v5"]
)
def test_every_paper_env_ships_a_validated_rescue_region(env: str) -> None:
    spec = load_spec(TUNING / f"{env}.pidlab-rescue.toml")
    region = load_region(spec)
    assert region.kind == "rescue"
    p = spec.bounds["rescue"]["provenance"]
    assert p["validation_samples"] >= 2000 and p["validation_failures"] == 0
    assert "ellipsoid" in spec.bounds or "box" in spec.bounds  # the certified core is kept beside it


def test_an_experiment_whose_predictive_condition_has_no_rescue_region_starts_nothing(tmp_path: Path) -> None:
    from tests.helpers import COACH

    conditions = tmp_path / "conditions.toml"
    conditions.write_text(
        (COACH / "conditions.toml").read_text()
        + '\n[condition.bad]\ndescription = "no rescue region"\ncoach = "pidlab-robust"\n'
        'coaching = { mode = "takeover", region = "rescue", trigger = "predictive" }\n'
    )
    out = tmp_path / "exp"
    code, err = cli_in_process(
        "experiment", "--envs", IP, "--conditions", "none,bad", "--conditions-file", str(conditions),
        "--seeds", "1", "--steps", "1000", "--out", str(out),
    )  # fmt: skip
    assert code == 2 and not out.exists()
    assert "condition 'bad' on InvertedPendulum-v5" in err and "has no rescue region" in err


def test_a_rescue_region_naming_an_unknown_variable_is_refused_with_the_spec(tmp_path: Path) -> None:
    text = ROOM.read_text()
    start = text.index("[bounds.rescue]")
    bad = text[:start] + text[start:].replace('"hinge_pos"', '"hinge_angle"', 1)
    spec = tmp_path / "bad.toml"
    spec.write_text(bad)
    code, err = cli_in_process("analyze", str(spec))
    assert code == 2 and "'hinge_angle' is not an observation variable of InvertedPendulum-v5" in err
