"""Automatic tuning on the open-loop unstable pendulum: stabilizing, honest about what it achieved."""

from __future__ import annotations

import pytest

from pidlab.controller.analysis import analyze_coach
from pidlab.controller.autotune import tune
from pidlab.controller.pid import Coach
from pidlab.errors import PidlabError


def test_robust_tune_stabilizes_and_reports_truthfully(models):
    loaded = models["InvertedPendulum-v5"]
    result = tune(loaded, preset="robust", max_evaluations=150)
    a = analyze_coach(Coach(result.spec, loaded), loaded)
    assert a.stable
    # what the tuner reports as achieved is what analysis measures
    assert result.achieved_phase_margin == pytest.approx(a.discrete.margins[0].phase_margin_deg)
    assert result.achieved_bandwidth == pytest.approx(a.discrete.margins[0].bandwidth)
    prov = result.spec.provenance
    assert prov["asked_phase_margin_deg"] == 60.0 and prov["preset"] == "robust"
    assert {lp.name for lp in result.spec.loops} == {"pole", "cart"}


def test_bandwidth_target_is_followed(models):
    loaded = models["InvertedPendulum-v5"]
    result = tune(loaded, bandwidth=10.0, phase_margin=45.0, max_evaluations=200)
    assert result.asked_bandwidth == 10.0
    assert result.achieved_bandwidth == pytest.approx(10.0, rel=0.25)


def test_weak_preset_drops_the_cart_loop(models):
    result = tune(models["InvertedPendulum-v5"], preset="weak", max_evaluations=150)
    assert [lp.name for lp in result.spec.loops] == ["pole"]
    assert result.achieved_phase_margin < 40


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"preset": "fancy"}, "unknown preset"),
        ({"bandwidth": -1.0}, "positive frequency"),
        ({"phase_margin": 120.0}, "between 0 and 90"),
    ],
)
def test_bad_targets(models, kwargs, message):
    with pytest.raises(PidlabError, match=message) as err:
        tune(models["InvertedPendulum-v5"], **kwargs)
    (param,) = kwargs  # the message names the Python parameter, for the CLI to map to its flag
    assert err.value.param == param and str(err.value).startswith(f"{param}={kwargs[param]!r}: ")


def test_contact_rich_refinement_runs_on_the_real_env(models):
    """Mechanics only (a tiny budget): both starts are refined on the env and the result recorded."""
    result = tune(models["Hopper-v5"], max_evaluations=20, refine_evaluations=3)
    assert result.refined_return is not None
    assert result.spec.provenance["refined_mean_return_tuning_seeds"] == result.refined_return
    assert result.evaluations >= 20 + 2 * 3
