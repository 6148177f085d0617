"""``pidlab experiment --reuse``: runs shared between experiments are copied, and equal a fresh training."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import tomli_w
import tomllib

from pidlab.experiment.reuse import REUSED_NAME, copy_run, find_reuses
from pidlab.experiment.sweep import ExperimentError, plan, run_sweep
from pidlab.files import read_json
from pidlab.report.experiment import write_report
from pidlab.rl.rundir import read_csv_rows
from tests.helpers import cli_in_process
from tests.test_experiment import IP, tiny_recipe, tree_digest

SEED = 3


@pytest.fixture(scope="module")
def earlier(tmp_path_factory) -> tuple[Path, Path]:
    """An earlier experiment: ``none`` on seed 3 at 300 env steps (its recipe and its folder)."""
    tmp = tmp_path_factory.mktemp("earlier")
    recipe = tiny_recipe(tmp, steps=300)
    p = plan([IP], ["none"], [SEED], tmp / "a", recipe_files=[str(recipe)])
    assert run_sweep(p, workers=1, progress_bar=False).count("done") == 1
    return recipe, p.out


def _run(out: Path, cond: str = "none") -> Path:
    return out / "runs" / IP / cond / f"seed-{SEED}"


def test_a_reused_run_is_the_run_training_would_make(tmp_path, earlier):
    recipe, a = earlier
    p = plan([IP], ["none", "paper"], [SEED], tmp_path / "b", recipe_files=[str(recipe)])
    r = run_sweep(p, workers=1, progress_bar=False, reuse=[a])
    assert (r.count("reused"), r.count("done")) == (1, 1)
    fresh = plan([IP], ["none"], [SEED], tmp_path / "c", recipe_files=[str(recipe)])
    assert run_sweep(fresh, workers=1, progress_bar=False).count("done") == 1
    for name in ("episodes.csv", "evaluations.csv"):  # the copy equals a training of the same settings
        assert read_csv_rows(_run(p.out) / name) == read_csv_rows(_run(fresh.out) / name)
    # the copy keeps its training's record and says where it came from
    assert read_json(_run(p.out) / "run.json") == read_json(_run(a) / "run.json")
    origin = read_json(_run(p.out) / REUSED_NAME)
    assert origin["from"] == str(_run(a).resolve()) and origin["experiment"] == str(a.resolve())
    assert origin["digest"] == p.tasks[0].digest
    record = read_json(p.out / "experiment.json")
    assert list(record["reused"]) == [f"{IP}/none/{SEED}"]
    assert "Copied, not trained" in write_report(p, progress_bar=False).read_text()
    # the same command again: both runs are finished here, nothing is copied or trained
    again = run_sweep(p, workers=1, progress_bar=False, reuse=[a])
    assert (again.count("skipped"), again.count("reused")) == (2, 0)


def test_other_settings_unfinished_or_started_runs_are_not_copied(tmp_path, earlier):
    recipe, a = earlier
    src = tmp_path / "a"
    shutil.copytree(a, src)
    assert len(find_reuses(plan([IP], ["none"], [SEED], tmp_path / "b", recipe_files=[str(recipe)]).tasks,
                           [src], tmp_path / "b")) == 1  # fmt: skip
    other = plan([IP], ["none"], [SEED], tmp_path / "b", recipe_files=[str(recipe)], steps=400)
    assert find_reuses(other.tasks, [src], other.out) == ()  # another budget: another digest
    same = plan([IP], ["none"], [SEED], tmp_path / "b", recipe_files=[str(recipe)])
    shutil.copytree(_run(src) / "checkpoints", _run(same.out) / "checkpoints")
    assert find_reuses(same.tasks, [src], same.out) == ()  # started here: resumed, never overwritten
    shutil.rmtree(same.out)
    (_run(src) / "summary.json").unlink()
    assert find_reuses(same.tasks, [src], same.out) == ()  # unfinished there: trained here


def _other_sac_table(recipe: Path, folder: Path) -> Path:
    """The recipe with its [sac] table changed (a table the PPO runs do not use)."""
    data = tomllib.loads(recipe.read_text())
    data["sac"]["learning_starts"] = int(data["sac"].get("learning_starts", 100)) + 1
    changed = folder / "changed.toml"
    changed.write_text(tomli_w.dumps(data))
    return changed


def test_a_run_is_known_by_what_it_used_not_by_the_tables_it_did_not(tmp_path, earlier):
    recipe, a = earlier
    changed = _other_sac_table(recipe, tmp_path)
    p = plan([IP], ["none"], [SEED], tmp_path / "b", recipe_files=[str(changed)])
    # a PPO run's settings digest ignores the [sac] table: the earlier run is the same run
    assert p.tasks[0].digest == plan([IP], ["none"], [SEED], tmp_path / "c", recipe_files=[str(recipe)]).tasks[0].digest
    assert len(find_reuses(p.tasks, [a], p.out)) == 1
    sac = plan([IP], ["none"], [SEED], tmp_path / "d", recipe_files=[str(changed)], algo="sac")
    assert find_reuses(sac.tasks, [a], sac.out) == ()  # another algorithm: another run


def test_an_older_record_is_read_by_its_runs_own_settings_and_made_current(tmp_path, earlier):
    recipe, a = earlier
    old = tmp_path / "old"
    shutil.copytree(a, old)
    record = read_json(old / "experiment.json")
    identity = record["identity"]
    identity.pop("digests")  # as written before digests covered the run's own algorithm only
    identity["runs"] = {k: "0123456789abcdef" for k in identity["runs"]}  # digests of the older kind
    (old / "experiment.json").write_text(json.dumps(record))
    changed = _other_sac_table(recipe, tmp_path)
    again = run_sweep(plan([IP], ["none"], [SEED], old, recipe_files=[str(changed)]), workers=1, progress_bar=False)
    assert again.count("skipped") == 1  # the same experiment: its run recorded the same settings
    upgraded = read_json(old / "experiment.json")["identity"]
    assert upgraded["digests"] == 2 and upgraded["runs"] != identity["runs"]
    # a run that recorded other settings (another budget) is another experiment: refused, unchanged
    (old / "experiment.json").write_text(json.dumps(record))
    with pytest.raises(ExperimentError, match="holds another experiment"):
        run_sweep(plan([IP], ["none"], [SEED], old, recipe_files=[str(recipe)], steps=400), workers=1,
                  progress_bar=False)  # fmt: skip
    assert read_json(old / "experiment.json") == record


def test_a_copy_killed_halfway_or_a_run_killed_before_its_checkpoint_is_replaced(tmp_path, earlier):
    recipe, a = earlier
    p = plan([IP], ["none"], [SEED], tmp_path / "b", recipe_files=[str(recipe)])
    target = _run(p.out)
    partial = target.with_name(f".{target.name}.reuse-partial")
    partial.mkdir(parents=True)
    (partial / "episodes.csv").write_text("cut")
    target.mkdir()
    (target / "config.toml").write_text("# killed before its first checkpoint\n")
    (reuse,) = find_reuses(p.tasks, [a], p.out)
    copy_run(reuse)
    assert not partial.exists() and not target.with_name(f".{target.name}.reuse-old").exists()
    expected = tree_digest(_run(a))
    got = tree_digest(target)
    assert got.pop(REUSED_NAME) and got == expected


def test_bad_reuse_is_one_line_and_exit_2_and_writes_nothing(tmp_path, earlier):
    recipe, a = earlier
    out = tmp_path / "b"
    base = ["experiment", "--envs", IP, "--conditions", "none", "--seeds", f"{SEED}-{SEED}",
            "--recipe", str(recipe), "--out", str(out), "--no-progress"]  # fmt: skip
    damaged = tmp_path / "damaged"
    shutil.copytree(a, damaged)
    (damaged / "experiment.json").write_text('{"schema": "pidlab.experiment/1", "ident')
    cut = tmp_path / "cut"
    shutil.copytree(a, cut)
    episodes = _run(cut) / "episodes.csv"
    episodes.write_text(episodes.read_text().splitlines()[0] + "\n1,2\n")
    stranger = tmp_path / "stranger"
    stranger.mkdir()
    cases = {
        str(tmp_path / "missing"): "no such folder",
        str(out): "this experiment's own folder",
        str(stranger): "holds no experiment.json",
        str(damaged): "experiment.json",
        str(cut): "logs are damaged",
    }
    for folder, message in cases.items():
        code, stderr = cli_in_process(*base, "--reuse", folder)
        assert code == 2 and message in stderr and "Traceback" not in stderr, (folder, stderr)
        assert len(stderr.strip().splitlines()) == 1, stderr
        assert not (out / "runs").exists()
    code, stderr = cli_in_process(*base, "--reuse", str(a), "--report-only")
    assert code == 2 and "--report-only" in stderr and len(stderr.strip().splitlines()) == 1
    p = plan([IP], ["none"], [SEED], out, recipe_files=[str(recipe)])
    for bad in (str(a), [1], None):
        with pytest.raises(ExperimentError, match="reuse"):
            run_sweep(p, workers=1, progress_bar=False, reuse=bad)  # type: ignore[arg-type]
    assert json.loads((a / "experiment.json").read_text())["identity"]  # the earlier one is untouched
