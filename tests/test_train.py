"""The trainer: accounting, determinism, agent-alone evaluation, checkpoints and resume after a kill.

Mechanics, not luck: budgets are a few thousand env steps and nothing here asserts that an
agent learned.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import gymnasium as gym
import pytest
import tomli_w

from pidlab.controller.spec import load_spec
from pidlab.files import read_json
from pidlab.rl.recipe import load_recipe, parse_recipe
from pidlab.rl.rundir import latest_checkpoint, read_csv_rows
from pidlab.rl.train import resume, train
from tests.helpers import cli_in_process

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]
IP = "InvertedPendulum-v5"
PIDLAB = str(Path(sys.executable).with_name("pidlab"))


def tiny_recipe(tmp_path: Path, name: str = "tiny.toml", **changes) -> Path:
    """The shipped IP recipe with a small budget and frequent evaluation/checkpoints."""
    data = tomllib.loads((ROOT / "coach" / f"{IP}.toml").read_text())
    data["steps"] = 3000
    data["evaluation"] = {"every": 1000, "episodes": 2, "seed": 123}
    data["checkpoint"] = {"every": 1000}
    data["sac"]["learning_starts"] = 200
    data["sac"]["buffer_size"] = 5000
    data["ppo"].pop("n_envs")  # one env (the zoo's rollout): each episode's steps add up to the totals
    data["ppo"]["n_steps"] = 32
    for key, value in changes.items():
        if isinstance(value, dict) and isinstance(data.get(key), dict):
            data[key].update(value)
        else:
            data[key] = value
    path = tmp_path / name
    path.write_text(tomli_w.dumps(data))
    return path


@pytest.fixture(scope="module")
def ip_spec():
    return load_spec(ROOT / "tuning" / f"{IP}.pidlab-robust.toml")


def rows(run: Path, name: str = "episodes.csv") -> list[dict[str, str]]:
    return read_csv_rows(run / name)


def test_accounts_add_up_in_the_logs(tmp_path, ip_spec):
    recipe = load_recipe(tiny_recipe(tmp_path))
    result = train(recipe, ip_spec, tmp_path / "run", progress_bar=False)
    assert result.completed and result.env_steps >= 3000 and result.coach_steps > 0
    assert result.env_steps == result.agent_steps + result.coach_steps
    eps = rows(tmp_path / "run")
    assert len(eps) == result.episodes > 0
    previous = 0
    for i, r in enumerate(eps):  # one env: each episode's steps are the increment of the totals
        assert int(r["episode"]) == i
        assert int(r["env_steps_so_far"]) - previous == int(r["agent_steps"]) + int(r["coach_steps"])
        previous = int(r["env_steps_so_far"])
        if int(r["coach_steps"]) == 0:
            assert float(r["total_return"]) == float(r["agent_return"])
    # the evaluation runs at step 0, every 1000 env steps and at the end
    ev = rows(tmp_path / "run", "evaluations.csv")
    steps = [int(r["env_steps_so_far"]) for r in ev]
    assert steps[0] == 0 and steps[-1] == result.env_steps and len(steps) >= 4
    run = tmp_path / "run"
    for name in ("config.toml", "coach.toml", "run.json", "summary.json", "final_model.zip", "final_vecnormalize.npz"):
        assert (run / name).exists(), name
    assert list((run / "tb").glob("events.out.tfevents.*")) and list((run / "tb" / "sb3").glob("events.*"))


def test_vectorized_coaching_keeps_the_accounts_per_env(tmp_path, ip_spec):
    """Four envs in one process, each with its own coach: every env's episodes add up, and the run repeats."""
    recipe = load_recipe(tiny_recipe(tmp_path, n_envs=4, steps=2000))
    result = train(recipe, ip_spec, tmp_path / "run", progress_bar=False)
    assert result.env_steps == result.agent_steps + result.coach_steps >= 2000
    assert result.agent_steps % 4 == 0  # one agent step of every env per vector step
    eps = rows(tmp_path / "run")
    assert {r["env_index"] for r in eps} == {"0", "1", "2", "3"}
    for i in "0123":
        mine = [r for r in eps if r["env_index"] == i]
        agent = sum(int(r["agent_steps"]) for r in mine)
        # this env's finished episodes, plus at most one unfinished episode (under 1000 steps)
        assert result.agent_steps // 4 - 1000 < agent <= result.agent_steps // 4
        assert sum(int(r["coach_steps"]) for r in mine) > 0  # its coach took over
    assert sum(int(r["coach_steps"]) for r in eps) <= result.coach_steps
    train(recipe, ip_spec, tmp_path / "again", progress_bar=False)
    for name in ("episodes.csv", "evaluations.csv"):
        assert (tmp_path / "run" / name).read_text() == (tmp_path / "again" / name).read_text()


def test_run_directory_records_what_reproduces_it(tmp_path, ip_spec):
    import json

    recipe = load_recipe(tiny_recipe(tmp_path))
    train(recipe, ip_spec, tmp_path / "run", progress_bar=False, argv=["pidlab", "train", "x"])
    info = json.loads((tmp_path / "run" / "run.json").read_text())
    assert info["seed"] == 0 and info["command"] == ["pidlab", "train", "x"]
    assert {"torch", "stable-baselines3", "gymnasium", "mujoco", "pidlab"} <= set(info["versions"])
    assert "sha" in info["git"]
    assert info["schema"] == "pidlab.run/1" and info["created"] and info["resumes"] == []
    config = tomllib.loads((tmp_path / "run" / "config.toml").read_text())
    again = parse_recipe(config["recipe"])
    assert again.steps == recipe.steps and again.algorithms == recipe.algorithms
    assert config["coach"]["name"] == "pidlab-robust" and len(config["coach"]["sha256"]) == 64
    assert load_spec(tmp_path / "run" / "coach.toml") == ip_spec


def test_same_seed_same_learning_curve(tmp_path, ip_spec):
    path = tiny_recipe(tmp_path, coaching={"probability": 0.7})  # the coin is seeded too
    recipe = load_recipe(path)
    a = train(recipe, ip_spec, tmp_path / "a", progress_bar=False)
    b = train(recipe, ip_spec, tmp_path / "b", progress_bar=False)
    assert (a.env_steps, a.coach_steps, a.episodes) == (b.env_steps, b.coach_steps, b.episodes)
    for name in ("episodes.csv", "evaluations.csv"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()
    c = train(load_recipe(tiny_recipe(tmp_path, "seed1.toml", seed=1, coaching={"probability": 0.7})), ip_spec,
              tmp_path / "c", progress_bar=False)  # fmt: skip
    assert (tmp_path / "c" / "episodes.csv").read_bytes() != (tmp_path / "a" / "episodes.csv").read_bytes()
    assert c.completed


def test_evaluation_is_the_agent_alone_on_the_bare_env(tmp_path, ip_spec):
    from pidlab.rl.agent import load_agent

    recipe = load_recipe(tiny_recipe(tmp_path))
    result = train(recipe, ip_spec, tmp_path / "run", progress_bar=False)
    agent = load_agent(tmp_path / "run")  # the final agent, read without unpickling
    env = gym.make(IP)  # no coach anywhere
    returns = []
    for seed in (123, 124):
        obs, _ = env.reset(seed=seed)
        total, done = 0.0, False
        while not done:
            action = agent.act(obs)
            obs, r, te, tr, _ = env.step(action)
            total += float(r)
            done = te or tr
        returns.append(total)
    assert result.final_evaluation is not None
    assert list(result.final_evaluation.returns) == returns


def test_uncoached_run_has_no_coach_steps(tmp_path):
    recipe = load_recipe(tiny_recipe(tmp_path))
    result = train(recipe, None, tmp_path / "run", progress_bar=False)
    assert result.coach_steps == 0 and result.env_steps == result.agent_steps == 3000
    assert all(r["coach_steps"] == "0" and r["agent_return"] == r["total_return"] for r in rows(tmp_path / "run"))
    assert not (tmp_path / "run" / "coach.toml").exists()
    # PPO trains on every full rollout of 32 steps: 93 of them, 5 epochs of one 32-step batch each
    summary = read_json(tmp_path / "run" / "summary.json")
    assert summary["policy_updates"] == 5 * (3000 // 32)


def _kill_after_checkpoint(cmd: list[str], run: Path, sig: int) -> tuple[int, int]:
    """Start ``cmd``; once a checkpoint exists and more episodes were logged after it, send ``sig``."""
    import json

    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.time() + 120
    kept = -1
    while time.time() < deadline and proc.poll() is None:
        states = sorted((run / "checkpoints").glob("*/state.json")) if (run / "checkpoints").exists() else []
        if states:
            kept = json.loads(states[-1].read_text())["episodes"]
            if len(rows(run)) > kept + 2:
                proc.send_signal(sig)
                break
        time.sleep(0.02)
    proc.wait(timeout=60)
    return proc.returncode, kept


def test_resume_after_a_kill_loses_no_episode(tmp_path, ip_spec):
    path = tiny_recipe(tmp_path, steps=8000, checkpoint={"every": 2000})
    spec_file = str(ROOT / "tuning" / f"{IP}.pidlab-robust.toml")
    full = train(load_recipe(path), ip_spec, tmp_path / "full", progress_bar=False)
    run = tmp_path / "killed"
    cmd = [PIDLAB, "train", IP, "--coach", spec_file, "--recipe", str(path), "--run-dir", str(run), "--no-progress"]
    code, _ = _kill_after_checkpoint(cmd, run, signal.SIGKILL)
    assert code == -signal.SIGKILL, "the run finished before it could be killed"
    assert not (run / "summary.json").exists()
    import json

    state = json.loads((latest_checkpoint(run) / "state.json").read_text())
    logged_before = rows(run)
    assert len(logged_before) > state["episodes"]  # episodes after the checkpoint were logged, then lost
    done = subprocess.run([PIDLAB, "train", IP, "--resume", str(run), "--no-progress"], capture_output=True,
                          text=True, timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr
    resumed, reference = rows(run), rows(tmp_path / "full")
    n = state["episodes"]
    assert n > 0
    assert resumed[:n] == reference[:n]  # up to the checkpoint: the uninterrupted run's episodes, exactly
    assert [int(r["episode"]) for r in resumed] == list(range(len(resumed)))  # none lost, none twice
    summary = json.loads((run / "summary.json").read_text())
    assert summary["completed"] and summary["env_steps"] >= 8000 and summary["resumes"] == 1
    assert int(resumed[-1]["env_steps_so_far"]) <= summary["env_steps"]
    ev = rows(run, "evaluations.csv")
    assert ev[: state["evaluations"]] == rows(tmp_path / "full", "evaluations.csv")[: state["evaluations"]]
    assert full.completed
    info = json.loads((run / "run.json").read_text())
    assert info["resumes"][0]["from_env_steps"] == state["env_steps"]
    entry = info["resumes"][0]
    assert entry["at"] and entry["versions"]["mujoco"] and "time" not in entry


def test_a_run_written_before_the_provenance_module_resumes(tmp_path):
    """run.json as pidlab wrote it before (``started``, resumes keyed ``time``): resumed and migrated."""
    import json

    every = {"every": 200}
    path = tiny_recipe(tmp_path, steps=400, checkpoint=every, evaluation={**every, "episodes": 1})
    run = tmp_path / "run"
    train(load_recipe(path), None, run, progress_bar=False)
    info = json.loads((run / "run.json").read_text())
    old = {k: info[k] for k in ("seed", "env_id", "coach", "algo", "command")}
    old |= {"started": info["created"], "versions": info["versions"], "git": info["git"],
            "resumes": [{"time": "2026-11-22T22:00:00+0000", "from_env_steps": 200, "budget_env_steps": 400,
                         "command": ["pidlab", "train"], "git": info["git"]}]}  # fmt: skip
    (run / "run.json").write_text(json.dumps(old))
    state_file = latest_checkpoint(run) / "state.json"  # nor did its checkpoints count policy updates
    state_file.write_text(json.dumps({k: v for k, v in json.loads(state_file.read_text()).items()
                                      if k != "policy_updates"}))  # fmt: skip
    assert resume(run, steps=600, progress_bar=False).completed
    # SB3's own count before the resume (12 rollouts of 32 steps, 5 epochs each), pidlab's after it
    assert read_json(run / "summary.json")["policy_updates"] == 5 * (400 // 32) + 5 * (200 // 32)
    new = json.loads((run / "run.json").read_text())
    assert new["created"] == info["created"] and "started" not in new and new["schema"] == "pidlab.run/1"
    assert new["resumes"][0]["at"] == "2026-11-22T22:00:00+0000" and len(new["resumes"]) == 2
    assert new["resumes"][1]["budget_env_steps"] == 600 and all("time" not in r for r in new["resumes"])


@pytest.mark.parametrize("cut", [4, 2])
def test_a_run_logged_before_env_episodes_were_counted_resumes_and_derives_them(tmp_path, cut):
    """episodes.csv without env_end/fell (cut 4) or without the runs (cut 2), and state.json without
    the env counters: upgraded on resume."""
    import json

    from pidlab.rl.rundir import EPISODE_COLUMNS, LEGACY_EPISODE_COLUMNS

    every = {"every": 200}
    path = tiny_recipe(tmp_path, steps=400, checkpoint=every, evaluation={**every, "episodes": 1})
    run = tmp_path / "run"
    train(load_recipe(path), None, run, progress_bar=False)
    lines = (run / "episodes.csv").read_text().splitlines()
    assert lines[0] == ",".join(EPISODE_COLUMNS)
    (run / "episodes.csv").write_text("".join(",".join(line.split(",")[:-cut]) + "\n" for line in lines))
    state_file = latest_checkpoint(run) / "state.json"
    state = json.loads(state_file.read_text())
    state_file.write_text(
        json.dumps({k: v for k, v in state.items() if k not in ("env_episodes", "env_resets", "falls")})
    )
    assert resume(run, steps=600, progress_bar=False).completed
    eps = rows(run)
    assert (
        (run / "episodes.csv").read_text().splitlines()[0]
        == ",".join(EPISODE_COLUMNS)
        != ",".join(LEGACY_EPISODE_COLUMNS)
    )
    assert all(r["env_end"] == "1" and r["fell"] == r["terminated"] for r in eps)  # no terminal view then
    kept = [r for r in eps if r["runs"] == "nan"]  # the episodes before the checkpoint: runs unknown
    assert kept and all(r["longest_run"] == "nan" for r in kept)
    assert all(r["runs"] == "1" for r in eps[len(kept):])  # no coach: one run per episode
    s = read_json(run / "summary.json")
    assert s["falls"] == sum(int(r["terminated"]) for r in eps)
    assert s["env_episodes"] == len(eps) and s["env_resets"] == len(eps) + 2  # one env, two sessions


def test_sigterm_stops_with_a_checkpoint_and_resumes(tmp_path):
    path = tiny_recipe(tmp_path, steps=8000, checkpoint={"every": 2000})
    run = tmp_path / "run"
    cmd = [PIDLAB, "train", IP, "--coach", "none", "--recipe", str(path), "--run-dir", str(run), "--no-progress"]
    code, _ = _kill_after_checkpoint(cmd, run, signal.SIGTERM)
    assert code == 130
    import json

    summary = json.loads((run / "summary.json").read_text())
    assert not summary["completed"]
    stop_state = json.loads((latest_checkpoint(run) / "state.json").read_text())
    assert stop_state["episodes"] == len(rows(run))  # the stop checkpoint keeps every logged episode
    twin = tmp_path / "twin"
    import shutil

    shutil.copytree(run, twin)
    result = resume(run, progress_bar=False)
    assert result.completed and result.env_steps >= 8000
    resumed = json.loads((run / "summary.json").read_text())  # the wall time adds up over the sessions
    assert summary["wall_s_total"] == summary["wall_s_last_session"] > 0
    assert resumed["wall_s_total"] == summary["wall_s_total"] + resumed["wall_s_last_session"]
    again = resume(twin, progress_bar=False)  # the same checkpoint resumed twice: the same continuation
    for name in ("episodes.csv", "evaluations.csv"):
        assert (run / name).read_bytes() == (twin / name).read_bytes()
    assert again.env_steps == result.env_steps


def test_sac_resume_keeps_the_replay_buffer(tmp_path, ip_spec):
    path = tiny_recipe(tmp_path, algo="sac", steps=600, checkpoint={"every": 300}, evaluation={"every": 300})
    run = tmp_path / "sac"
    result = train(load_recipe(path), None, run, progress_bar=False)  # uncoached: 600 agent steps, 400 trained
    assert result.completed and result.agent_steps == 600
    before = read_json(run / "summary.json")["policy_updates"]
    checkpoint = latest_checkpoint(run)
    assert checkpoint is not None and (checkpoint / "replay_buffer.npz").exists()
    extended = resume(run, steps=900, progress_bar=False)  # a longer budget continues the run
    assert extended.completed and extended.env_steps >= 900 and extended.agent_steps > result.agent_steps
    after = read_json(run / "summary.json")["policy_updates"]
    assert 0 < before < after <= before + 300 + 8  # the count goes on across the resume: 8 per 8 steps at most
    from stable_baselines3 import SAC

    from pidlab.rl.checkpoint import load_buffer

    model = SAC.load(run / "final_model.zip", device="cpu")  # SB3's own format, for SB3 users
    assert model.num_timesteps == extended.agent_steps == 900
    assert model.replay_buffer.size() == 0  # the final model is the policy; the buffer lives in the checkpoint
    load_buffer(latest_checkpoint(run) / "replay_buffer.npz", model.replay_buffer)
    assert model.replay_buffer.size() == 900  # 600 before the resume, kept, and 300 after


def test_subproc_vec_env_counts_every_env(tmp_path, ip_spec):
    recipe = load_recipe(tiny_recipe(tmp_path, n_envs=2, vec_env="subproc", steps=2000))
    result = train(recipe, ip_spec, tmp_path / "run", progress_bar=False)
    eps = rows(tmp_path / "run")
    assert {r["env_index"] for r in eps} == {"0", "1"}
    assert result.env_steps == result.agent_steps + result.coach_steps >= 2000
    done_steps = sum(int(r["agent_steps"]) + int(r["coach_steps"]) for r in eps)
    assert done_steps <= result.env_steps


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--coach", "none", "--algo", "td3"], "--algo 'td3'"),
        (["--coach", "none", "--steps", "0"], "--steps 0"),
        (["--coach", "nosuch"], "expected none, a coach spec file"),
        (["--coach", str(ROOT / "tuning" / "Hopper-v5.pidlab-robust.toml")], "the spec is for Hopper-v5"),
        (["--coach", "none", "--recipe", str(ROOT / "coach" / "Hopper-v5.toml")], "the recipe is for Hopper-v5"),
        (["--coach", "none", "--recipe", "/nonexistent.toml"], "cannot read recipe"),
        ([], "--coach: required"),
        (["--coach", "paper"], "the spec has no [bounds.box]; run `pidlab bounds SPEC --write`"),
        (["--resume", "/nonexistent-run"], "not a pidlab run directory"),
    ],
)
def test_cli_bad_input_is_one_line_and_exit_2(tmp_path, args, message):
    code, stderr = cli_in_process("train", IP, *args, "--run-dir", str(tmp_path / "r"))
    assert code == 2, stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], stderr
    assert not (tmp_path / "r").exists()


def test_cli_bad_input_from_the_real_executable(tmp_path):
    done = subprocess.run([PIDLAB, "train", IP, "--coach", "none", "--algo", "td3", "--run-dir",
                           str(tmp_path / "r")], capture_output=True, text=True, timeout=120)  # fmt: skip
    assert done.returncode == 2 and done.stderr.strip().splitlines() == [
        "pidlab: error: --algo 'td3': expected one of ppo, sac"
    ]
    assert not (tmp_path / "r").exists()


def test_cli_refuses_to_overwrite_a_run(tmp_path):
    path = tiny_recipe(tmp_path, steps=200, evaluation={"every": 200, "episodes": 1})
    base = [PIDLAB, "train", IP, "--coach", "none", "--recipe", str(path), "--run-dir", str(tmp_path / "r")]
    first = subprocess.run([*base, "--no-progress"], capture_output=True, text=True, timeout=120)
    assert first.returncode == 0, first.stderr
    before = (tmp_path / "r" / "episodes.csv").read_bytes()
    code, stderr = cli_in_process(*base[1:], "--no-progress")
    assert code == 2 and "exists and is not empty" in stderr
    assert (tmp_path / "r" / "episodes.csv").read_bytes() == before
    code, stderr = cli_in_process("train", IP, "--resume", str(tmp_path / "r"), "--seed", "3")
    assert code == 2 and "--seed differs" in stderr


def test_growth_trigger_runs_the_papers_nudge(tmp_path, ip_spec):
    """The paper's coded IP rule: one coach step when |hinge_vel| <= 0.3 grew twice in a row."""
    paper = load_spec(ROOT / "tuning" / f"{IP}.paper.toml")
    trigger = {"variable": "hinge_vel", "low": 0.0, "high": 0.3, "steps": 2}
    path = tiny_recipe(tmp_path, steps=1500, coaching={"mode": "nudge", "trigger": trigger})
    result = train(load_recipe(path), paper, tmp_path / "run", progress_bar=False)
    assert result.coach_steps == result.interventions > 0  # exactly one coach step per nudge
    assert result.env_steps == result.agent_steps + result.coach_steps


def test_fading_schedule_reaches_the_envs(tmp_path, ip_spec):
    """With coaching off after 30 % of the budget, no coach step happens after that point."""
    path = tiny_recipe(tmp_path, steps=4000, coaching={"off_after": 0.3})
    result = train(load_recipe(path), ip_spec, tmp_path / "run", progress_bar=False)
    assert result.coach_steps > 0
    late = [r for r in rows(tmp_path / "run") if int(r["env_steps_so_far"]) - int(r["agent_steps"])
            - int(r["coach_steps"]) >= 0.3 * 4000 + 10]  # fmt: skip  (episodes that started after the switch)
    assert late and all(r["coach_steps"] == "0" for r in late)


def test_no_stray_files_after_a_run(tmp_path, ip_spec):
    recipe = load_recipe(tiny_recipe(tmp_path, steps=500, evaluation={"every": 500, "episodes": 1}))
    train(recipe, ip_spec, tmp_path / "run", progress_bar=False)
    stray = [p for p in (tmp_path / "run").rglob("*") if p.name.endswith(".tmp") or ".tmp." in p.name]
    assert not stray
    assert len(list((tmp_path / "run" / "checkpoints").iterdir())) == 1


def test_training_runs_blas_on_the_recipes_threads_and_gives_them_back(tmp_path, monkeypatch):
    """The coach's numpy numerics (classifier scores, the model predictor's bounds) run on the recipe's
    threads, as torch does; the caller's BLAS settings are back afterwards."""
    from threadpoolctl import threadpool_info, threadpool_limits

    import pidlab.rl.train as train_module

    seen = []
    monkeypatch.setattr(train_module, "_session", lambda *args: seen.append(threadpool_info()) or "done")
    recipe = load_recipe(tiny_recipe(tmp_path, threads=1))
    with threadpool_limits(limits=2, user_api="blas"):
        before = [pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"]
        assert train_module._run(recipe, None, tmp_path / "run", False, lambda venv: None) == "done"
        after = [pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"]
    blas = [pool["num_threads"] for pool in seen[0] if pool["user_api"] == "blas"]
    assert blas and all(n == 1 for n in blas)
    assert after == before and before and all(n == 2 for n in before)
