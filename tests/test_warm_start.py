"""Coach demonstrations and the warm start: what is collected, what is charged, what the clone can do."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import tomli_w
import tomllib

from pidlab.controller.pid import Coach
from pidlab.controller.spec import load_spec
from pidlab.errors import CoachingError, RecipeError
from pidlab.plant.model import load_model
from pidlab.rl import demonstrations as demo
from pidlab.rl.cloning import discounted_returns
from pidlab.rl.recipe import load_recipe, parse_recipe
from pidlab.rl.train import train
from tests.helpers import ROOT, TUNING, cli_in_process

IP = "InvertedPendulum-v5"


def _recipe_data(steps: int, coaching: dict, every: int = 500, episodes: int = 2) -> dict:
    data = tomllib.loads((ROOT / "coach" / f"{IP}.toml").read_text())
    data["steps"] = steps
    data["evaluation"] = {"every": every, "episodes": episodes, "seed": 1000000}
    data["checkpoint"] = {"every": 100000}
    data["coaching"] = {**data["coaching"], "off_after": 0.0, **coaching}
    return data


def _recipe_file(tmp_path: Path, steps: int, coaching: dict, **kw) -> Path:
    path = tmp_path / "ws.toml"
    path.write_text(tomli_w.dumps(_recipe_data(steps, coaching, **kw)))
    return path


def _rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


# ------------------------------------------------------------------------------- recipe fields


@pytest.mark.parametrize(
    ("coaching", "message"),
    [
        ({"demonstrations": {"steps": -5}}, "demonstrations.steps"),
        ({"demonstrations": {"noise": 0.1}}, "demonstrations.steps: missing"),
        ({"demonstrations": {"steps": 100, "noise": -0.1}}, "demonstrations.noise"),
        ({"warm_start": {"epochs": 5}}, "a warm start clones the coach's demonstrations, and there are none"),
        ({"demonstrations": {"steps": 100}, "warm_start": {"epochs": 0}}, "warm_start.epochs"),
        ({"demonstrations": {"steps": 100, "speed": 1}}, "unknown field"),
    ],
)
def test_bad_teaching_fields_are_refused_by_name(coaching: dict, message: str) -> None:
    with pytest.raises(RecipeError, match="coaching.") as err:
        parse_recipe(_recipe_data(1000, coaching))
    assert message in str(err.value)


def test_teaching_fields_round_trip() -> None:
    from pidlab.rl.recipe import recipe_to_dict

    r = parse_recipe(_recipe_data(1000, {"demonstrations": {"steps": 300, "noise": 0.2}, "warm_start": {}}))
    assert r.coaching.demonstrations.steps == 300 and r.coaching.demonstrations.noise == 0.2
    assert r.coaching.warm_start.epochs == 30 and r.coaching.warm_start.critic
    assert parse_recipe(recipe_to_dict(r)) == r


def test_couplings_that_cannot_run_are_refused_before_any_file(tmp_path: Path) -> None:
    spec = load_spec(TUNING / f"{IP}.pidlab-rescue.toml")
    with_demos = load_recipe(_recipe_file(tmp_path, 1000, {"demonstrations": {"steps": 200}}))
    with pytest.raises(CoachingError, match="need a coach"):
        train(with_demos, None, tmp_path / "a", progress_bar=False)
    too_long = load_recipe(_recipe_file(tmp_path, 1000, {"demonstrations": {"steps": 1000}}))
    with pytest.raises(CoachingError, match="fewer env steps than the budget"):
        train(too_long, spec, tmp_path / "b", progress_bar=False)
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()
    code, out = cli_in_process("train", IP, "--coach", "none", "--recipe", str(tmp_path / "ws.toml"),
                               "--run-dir", str(tmp_path / "c"), "--no-progress")  # fmt: skip
    assert code == 2 and len(out.strip().splitlines()) == 1 and "demonstrations" in out


def test_a_warm_start_with_sac_is_refused(tmp_path: Path) -> None:
    from dataclasses import replace

    spec = load_spec(TUNING / f"{IP}.pidlab-rescue.toml")
    r = load_recipe(_recipe_file(tmp_path, 1000, {"demonstrations": {"steps": 200}, "warm_start": {}}))
    with pytest.raises(CoachingError, match="clones a PPO agent"):
        train(replace(r, algo="sac"), spec, tmp_path / "s", progress_bar=False)


# ------------------------------------------------------------------------------- the pieces


def test_discounted_returns_hand_computed() -> None:
    r = np.array([1.0, 2.0, 3.0, 4.0])
    ends = np.array([False, True, False, False])
    cut = np.array([False, False, False, True])
    boot = np.array([0.0, 0.0, 0.0, 10.0])
    # episode 1: G1 = 2, G0 = 1 + 0.5 * 2; episode 2 cut at its end: G3 = 4 + 0.5 * 10, G2 = 3 + 0.5 * 9
    assert discounted_returns(r, ends, cut, boot, 0.5).tolist() == [2.0, 2.0, 7.5, 9.0]


def test_demonstrations_round_trip_and_refuse_objects(tmp_path: Path) -> None:
    d = demo.Demonstrations(np.zeros((3, 4), np.float32), np.ones((3, 1), np.float32), np.arange(3.0),
                            np.array([False, False, True]), np.zeros(3, bool), np.zeros(3, np.int64))  # fmt: skip
    back = demo.load(demo.save(tmp_path / demo.FILE, d))
    assert all(np.array_equal(getattr(back, k), getattr(d, k)) for k in demo.FIELDS)
    np.savez(tmp_path / "bad.npz", obs=np.array([object()], dtype=object))
    with pytest.raises(CoachingError, match="not a demonstrations file"):
        demo.load(tmp_path / "bad.npz")


# ------------------------------------------------------------------------------- a run


@pytest.fixture(scope="module")
def warm_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A warm-started IP run: 400 noiseless demonstration steps on 4 envs, then 400 agent steps."""
    folder = tmp_path_factory.mktemp("warm")
    coaching = {"demonstrations": {"steps": 400, "noise": 0.0}, "warm_start": {"epochs": 2}}
    recipe = load_recipe(_recipe_file(folder, 800, coaching))
    spec = load_spec(TUNING / f"{IP}.pidlab-rescue.toml")
    train(recipe, spec, folder / "run", progress_bar=False)
    return folder / "run"


def test_every_demonstration_step_is_charged_and_logged(warm_run: Path) -> None:
    s = json.loads((warm_run / "summary.json").read_text())
    demos = demo.load(warm_run / demo.FILE)
    assert len(demos) == 400 and s["coach_steps"] == 400  # 100 rounds of 4 envs; no takeover after
    assert s["interventions"] == 0  # a demonstration step is no intervention
    assert s["env_steps"] == s["agent_steps"] + s["coach_steps"] >= 800
    episodes = _rows(warm_run / "episodes.csv")
    demo_eps = [e for e in episodes if int(e["agent_steps"]) == 0]
    assert sum(int(e["coach_steps"]) for e in episodes) <= 400
    assert all(float(e["agent_return"]) == 0.0 for e in demo_eps)
    assert s["falls"] == sum(int(e["fell"]) for e in episodes)
    assert s["env_episodes"] == sum(int(e["env_end"]) for e in episodes)
    # the demonstrations' falls are the logged ones: a terminated demonstration step ends a logged episode
    assert int(demos.terminated.sum()) == sum(int(e["fell"]) for e in demo_eps)
    # resets: the 4 envs once when the demonstrations start, then one per ended episode (none by SB3)
    assert s["env_resets"] == 4 + s["env_episodes"]


def test_noiseless_demonstrations_are_the_coachs_actions(warm_run: Path) -> None:
    demos = demo.load(warm_run / demo.FILE)
    coach = Coach(load_spec(TUNING / f"{IP}.pidlab-rescue.toml"), load_model(IP))
    rows = np.flatnonzero(demos.env_index == 0)
    start = True
    for t in rows:
        if start:
            coach.reset(demos.obs[t])
        expected = np.clip(coach.act(demos.obs[t]), -3.0, 3.0)
        np.testing.assert_allclose(demos.actions[t], expected, rtol=1e-5, atol=1e-6)
        start = bool(demos.terminated[t] or demos.truncated[t])


def test_the_warm_start_is_recorded_and_evaluated_before_any_update(warm_run: Path) -> None:
    record = json.loads((warm_run / "warm_start.json").read_text())
    assert record["demonstration_steps"] == 400 and record["env_steps_after"] == 400
    assert record["clone"]["samples"] == 400 and record["clone"]["epochs"] == 2
    evals = _rows(warm_run / "evaluations.csv")
    # at 0 (the initial agent), then right after the clone, at 400 env steps and 0 agent steps
    assert [(int(e["env_steps_so_far"]), int(e["agent_steps_so_far"])) for e in evals[:2]][-1] == (400, 0)
    assert float(evals[1]["mean_return"]) == record["agent_alone_after"]


def test_a_resumed_warm_run_does_not_demonstrate_again(warm_run: Path, tmp_path: Path) -> None:
    import shutil

    from pidlab.rl.train import resume

    copy = tmp_path / "copy"
    shutil.copytree(warm_run, copy)
    before = (copy / demo.FILE).read_bytes()
    done = resume(copy, steps=1200, progress_bar=False)
    s = json.loads((copy / "summary.json").read_text())
    assert done.completed and s["coach_steps"] == 400 and s["env_steps"] >= 1200
    assert (copy / demo.FILE).read_bytes() == before


def test_a_cloned_pendulum_balances_alone_before_any_rl_update(tmp_path: Path) -> None:
    # 5,000 noisy demonstrations of the rescue coach, cloned: the agent alone holds the pole for
    # the whole 1000-step episode on each of 10 evaluation seeds, before PPO's first update
    coaching = {"demonstrations": {"steps": 5000, "noise": 0.1}, "warm_start": {"epochs": 30}}
    recipe = load_recipe(_recipe_file(tmp_path, 5100, coaching, every=5000, episodes=10))
    spec = load_spec(TUNING / f"{IP}.pidlab-rescue.toml")
    train(recipe, spec, tmp_path / "run", progress_bar=False)
    evals = _rows(tmp_path / "run" / "evaluations.csv")
    after = next(e for e in evals if int(e["env_steps_so_far"]) == 5000)
    assert int(after["agent_steps_so_far"]) == 0
    assert float(after["mean_length"]) == 1000.0 and float(after["mean_return"]) == 1000.0


def test_sigterm_during_the_demonstrations_stops_after_the_warm_start(tmp_path: Path) -> None:
    import signal
    import subprocess
    import sys
    import time

    from pidlab.rl.train import resume

    coaching = {"demonstrations": {"steps": 40000, "noise": 0.1}, "warm_start": {"epochs": 1}}
    path = _recipe_file(tmp_path, 41000, coaching, every=100000)
    run = tmp_path / "run"
    pidlab = str(Path(sys.executable).parent / "pidlab")
    cmd = [pidlab, "train", IP, "--coach", "pidlab-rescue", "--recipe", str(path), "--run-dir", str(run),
           "--no-progress"]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None:
        if (run / "episodes.csv").exists() and len(_rows(run / "episodes.csv")) >= 2:  # demonstrating
            proc.send_signal(signal.SIGTERM)
            break
        time.sleep(0.02)
    proc.wait(timeout=120)
    assert proc.returncode == 130, proc.stderr.read() if proc.stderr else ""
    s = json.loads((run / "summary.json").read_text())
    # the demonstrations were finished, cloned and checkpointed; the agent never acted
    assert not s["completed"] and s["coach_steps"] == 40000 and s["agent_steps"] == 0
    assert (run / "warm_start.json").exists()
    before = (run / demo.FILE).read_bytes()
    done = resume(run, progress_bar=False)
    assert done.completed and done.coach_steps == 40000 and done.agent_steps >= 1000
    assert (run / demo.FILE).read_bytes() == before


# ------------------------------------------------------------------------------- the demonstrations kept

KEEP = {"shape": "linear", "start": 1.0, "end": 0.0, "begin": 0.0, "finish": 1.0}


@pytest.mark.parametrize(
    ("keep", "message"),
    [({"shape": "linear", "start": -1.0, "end": 0.0}, "schedule start = -1.0: expected a finite number >= 0"),
     ({"shape": "sideways"}, "schedule shape 'sideways'"), ("1", "expected a number >= 0 or a table")],
)  # fmt: skip
def test_a_bad_kept_demonstration_weight_is_refused(keep, message: str) -> None:
    coaching = {"demonstrations": {"steps": 100}, "warm_start": {"keep": keep}}
    with pytest.raises(RecipeError, match="warm_start.keep") as err:
        parse_recipe(_recipe_data(1000, coaching))
    assert message in str(err.value)


@pytest.mark.parametrize("keep", [0.5, {"shape": "constant", "start": 1.0, "end": 1.0}])
def test_a_kept_demonstration_weight_may_stay_above_zero(keep) -> None:
    """A loss on the demonstrations, not a coach's action: it need not fade (unlike blend and residual)."""
    coaching = {"demonstrations": {"steps": 100}, "warm_start": {"keep": keep}}
    kept = parse_recipe(_recipe_data(1000, coaching)).coaching.warm_start.keep
    assert kept is not None and kept(1.0) > 0.0 and kept(0.0) == kept(1.0)


def _kept_run(folder: Path, steps: int) -> Path:
    coaching = {"demonstrations": {"steps": 400, "noise": 0.1}, "warm_start": {"epochs": 2, "keep": KEEP}}
    data = _recipe_data(steps, coaching)
    data["checkpoint"] = {"every": 800}
    path = folder / "keep.toml"
    path.write_text(tomli_w.dumps(data))
    train(load_recipe(path), load_spec(TUNING / f"{IP}.pidlab-rescue.toml"), folder / "run", progress_bar=False)
    return folder / "run"


def _gradient_steps_add_up(run: Path) -> dict:
    """Each kept round takes as many gradient steps as a PPO update: 5 epochs x 1 batch of 32."""
    s = json.loads((run / "summary.json").read_text())
    from pidlab.rl.rundir import latest_checkpoint

    state = json.loads((latest_checkpoint(run) / "state.json").read_text())
    updates = state["sb3"]["n_updates"] // 5  # PPO's train() calls (SB3 counts epochs)
    assert s["kept_rounds"] >= 1 and updates - 1 <= s["kept_rounds"] <= updates
    assert s["policy_updates"] == 5 * (updates + s["kept_rounds"])
    return s


def test_kept_demonstrations_take_one_round_after_each_update(tmp_path: Path) -> None:
    s = _gradient_steps_add_up(_kept_run(tmp_path, 1200))
    assert s["kept_at"] > 0


def test_a_resumed_run_does_not_repeat_a_kept_round(tmp_path: Path) -> None:
    from pidlab.rl.train import resume

    run = _kept_run(tmp_path, 1200)
    before = json.loads((run / "summary.json").read_text())["kept_rounds"]
    resume(run, steps=2000, progress_bar=False)
    s = _gradient_steps_add_up(run)
    assert s["kept_rounds"] > before
