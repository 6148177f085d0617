"""The coach alone on the real env: deterministic per seed, failure causes named."""

from __future__ import annotations

from pathlib import Path

from pidlab.controller.rollout import coach_alone
from pidlab.controller.spec import load_spec

TUNING = Path(__file__).resolve().parents[1] / "tuning"


def test_paper_ip_coach_fails_on_pole_angle_and_is_reproducible(models):
    loaded = models["InvertedPendulum-v5"]
    spec = load_spec(TUNING / "InvertedPendulum-v5.paper.toml")
    a = coach_alone(spec, loaded, episodes=3)
    b = coach_alone(spec, loaded, episodes=3)
    assert a.returns.tolist() == b.returns.tolist()
    assert a.causes == {"hinge_pos outside [-0.2, 0.2]": 3}
    assert all(e.terminated and e.length < 1000 for e in a.episodes)


def test_robust_coach_survives_the_time_limit(models):
    loaded = models["InvertedPendulum-v5"]
    score = coach_alone(load_spec(TUNING / "InvertedPendulum-v5.pidlab-robust.toml"), loaded, episodes=3)
    assert score.causes == {"time limit": 3} and score.mean == 1000.0
