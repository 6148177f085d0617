"""Coach specs: exact round trips and validation of malformed files."""

from __future__ import annotations

from pathlib import Path

import pytest

from pidlab.controller.pid import Coach
from pidlab.controller.spec import dumps_spec, load_spec, loads_spec, parse_spec, save_spec
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
        ("kp = 15.0", 'kp = "fifteen"', "loop 'pole'.kp = 'fifteen': expected a finite number"),
        ("kp = 15.0", "kp = true", "loop 'pole'.kp = True: expected a finite number"),
        ("kp = 15.0", "kp = nan", "loop 'pole'.kp = nan: expected a finite number"),
        ("kp = 15.0", "kp = inf", "loop 'pole'.kp = inf: expected a finite number"),
        ("tf = 0.0", "tf = -0.01", "tf = -0.01: expected a finite number >= 0 (s)"),
        ("tt = 0.0", "tt = nan", "tt = nan: expected a finite number >= 0 (s)"),
        (
            "[loop.actuators]\nslide = 1.0",
            "[loop.actuators]\nslide = nan",
            "actuators.slide = nan: expected a finite",
        ),
        ("[loop.actuators]\nslide = 1.0", "[loop.actuators]\nslide = false", "actuators.slide = False"),
        ('name = "pole"', 'name = "po.le"', "name = 'po.le': expected a name of 1-64 letters"),
        ('anti_windup = "clamping"', 'anti_windup = "magic"', "allowed: none, clamping, back-calculation"),
        (
            'anti_windup = "clamping"',
            'anti_windup = "back-calculation"',
            "needs a tracking time constant > 0 s",
        ),
        ('action = "direct"', 'action = "sideways"', "allowed: reverse, direct"),
        ("kd = 2.25", "kd = 2.25\ngain = 3", "unknown field(s) ['gain']"),
        ('env_id = "InvertedPendulum-v5"', 'env_id = ""', "env_id = '': expected a name of 1-64 letters"),
        ('name = "paper"', 'name = "../../../../tmp/x"', "name = '../../../../tmp/x': expected a name of"),
        ('name = "paper"', 'name = "' + "x" * 100_000 + '"', "name = 'xxxxxxxxx"),
        ('name = "paper"', "name = 3", "name = 3: expected a name"),
        ("[loop.actuators]\nslide = 1.0", "[loop.actuators]", "give either actuators"),
        ("[loop.actuators]\nslide = 1.0", 'feeds = "nowhere"', "no loop 'nowhere'"),
        ("[loop.actuators]\nslide = 1.0", 'feeds = "pole"', "feeds itself"),
        ("output_limits = [\n    -inf,\n    inf,\n]", "output_limits = [1.0, -1.0]", "must be below high"),
        ("output_limits = [\n    -inf,\n    inf,\n]", "output_limits = [1.0]", "expected [low, high]"),
        ("output_limits = [\n    -inf,\n    inf,\n]", "output_limits = [nan, 1.0]", "(inf allowed, not nan)"),
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


ROBUST = TUNING / "InvertedPendulum-v5.pidlab-robust.toml"


def _robust() -> dict:
    import tomllib

    return tomllib.loads(ROBUST.read_text(encoding="utf-8"))


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda d: d.update(description=3), "description = 3: expected a string"),
        (
            lambda d: d["bounds"]["ellipsoid"].update(level=float("nan")),
            "ellipsoid.level = nan: expected a finite number > 0",
        ),
        (
            lambda d: d["bounds"]["ellipsoid"].update(level=0.0),
            "ellipsoid.level = 0.0: expected a finite number > 0",
        ),
        (lambda d: d["bounds"]["ellipsoid"].update(rho=True), "ellipsoid.rho = True"),
        (lambda d: d["bounds"]["ellipsoid"]["center"].__setitem__(0, float("nan")), "ellipsoid.center = nan"),
        (lambda d: d["bounds"]["ellipsoid"]["shape"][0].__setitem__(1, 1.0), "expected a symmetric matrix"),
        (
            lambda d: d["bounds"]["ellipsoid"].update(
                shape=[[-1.0 if i == j else 0.0 for j in range(4)] for i in range(4)]
            ),
            "expected a positive definite matrix",
        ),
        (lambda d: d["bounds"]["ellipsoid"].update(variables=["hinge_pos"] * 4), "a variable is named twice"),
        (
            lambda d: d["bounds"]["box"].update(hinge_pos=[False, True]),
            "box.hinge_pos = False: expected a finite number",
        ),
        (
            lambda d: d["bounds"]["box"].update(hinge_pos=[-1.0, float("inf")]),
            "box.hinge_pos = inf: expected a finite",
        ),
        (lambda d: d["bounds"].update(provenance=3), "bounds.provenance: expected a table"),
        (lambda d: d["offset"].update(slide=float("nan")), "offset.slide = nan: expected a finite number"),
    ],
)
def test_numbers_in_a_spec_are_checked(edit, message):
    data = _robust()
    edit(data)
    with pytest.raises(SpecError) as err:
        parse_spec(data, "s.toml")
    assert message in str(err.value)


def test_parse_spec_of_no_table_is_a_spec_error():
    for value in (None, [], "x", 3):
        with pytest.raises(SpecError, match="expected a table"):
            parse_spec(value, "s")  # type: ignore[arg-type]


def test_a_long_name_is_one_short_line():
    data = _robust()
    data["name"] = "x" * 100_000
    with pytest.raises(SpecError) as err:
        parse_spec(data, "s.toml")
    assert len(str(err.value)) < 200 and "\n" not in str(err.value)


def test_an_unstable_coachs_responses_plot_their_finite_part(models):
    """Walker2d's paper coach is unstable: its responses overflow; the plot draws them up to ``DIVERGED``."""
    import io

    import matplotlib.pyplot as plt
    import numpy as np

    from pidlab.controller.analysis import DIVERGED, analyze_coach, closed_loop_responses
    from pidlab.report.plots import plot_responses

    spec = load_spec(TUNING / "Walker2d-v5.paper.toml")
    coach = Coach(spec, models[spec.env_id])
    analysis = analyze_coach(coach, models[spec.env_id])
    assert not analysis.stable
    responses = closed_loop_responses(analysis, coach)
    for data in (responses.step, responses.initial):
        finite = np.isfinite(data)
        assert finite[:, 0].all() and not finite.all()  # starts finite, is cut where it diverges
        assert np.all(np.abs(data[finite]) <= DIVERGED)
        assert np.all(np.diff(finite.astype(int), axis=1) <= 0)  # once cut, stays cut
    fig = plot_responses(responses)
    fig.savefig(io.BytesIO(), format="png")  # raised OverflowError in the tick formatter before
    plt.close(fig)


@pytest.mark.parametrize(("kp", "weight"), [(-1e300, 1.0), (1e200, 1e200)])
def test_gains_that_overflow_the_analysis_name_the_loop(models, kp, weight):
    from pidlab.controller.analysis import analyze_coach
    from pidlab.errors import AnalysisError

    text = BASE.replace("kp = 15.0", f"kp = {kp!r}").replace("slide = 1.0", f"slide = {weight!r}")
    spec = loads_spec(text)
    loaded = models[spec.env_id]
    with pytest.raises(AnalysisError) as err:
        analyze_coach(Coach(spec, loaded), loaded)
    message = str(err.value)
    assert "loop 'pole'" in message and "\n" not in message
