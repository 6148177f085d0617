"""The published results are what pidlab's code computes from the published runs' logs.

Every experiment folder under docs/results/ ships its runs' episodes.csv, evaluations.csv,
summary.json and config.toml; benchmarks/recompute.py re-analyzes them. Here the same recompute
must give the committed metrics.csv, summary.csv and report.md byte for byte, so a change to the
measures that is not followed by regenerating the published reports fails. For a pipeline's
experiment, the section of the pipeline's own report.md that reads those runs ("The agent alone")
and its report.html must match too.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest

from tests.helpers import ROOT

sys.path.insert(0, str(ROOT / "benchmarks"))
import recompute

FOLDERS = recompute.published_folders()


def test_every_published_experiment_ships_its_runs():
    with_record = [p.parent for p in (ROOT / "docs" / "results").rglob("experiment.json")]
    assert with_record and sorted(with_record) == sorted(FOLDERS)


@pytest.mark.parametrize(
    "folder", FOLDERS, ids=[str(f.relative_to(ROOT / "docs" / "results")) for f in FOLDERS]
)
def test_a_published_report_is_recomputed_from_its_runs_logs(folder):
    a, texts = recompute.recompute(folder)
    for name in ("metrics.csv", "summary.csv", "report.md"):
        assert (folder / name).read_text() == texts[name], f"{folder / name}: run benchmarks/recompute.py"
    report = recompute.pipeline_report(folder)
    if report is not None:
        for name, text in recompute.pipeline_texts(a, report).items():
            committed = (report.parent / name).read_text()
            assert committed == text, f"{report.parent / name}: run benchmarks/recompute.py"


def test_the_results_pages_tables_come_from_the_summaries():
    assert recompute.check_readme() == []


def test_the_vectorization_page_comes_from_its_runs():
    """docs/vectorization.md, recomputed from the published runs' logs (benchmarks/vectorization.py --check)."""
    import vectorization

    figures = {(e, v): f"vectorization-{e}-{v}.png" for e, _, v, _ in vectorization.DESIGN}
    assert (ROOT / "docs" / "vectorization.md").read_text() == vectorization.page(figures)
    for name in figures.values():
        assert (ROOT / "docs" / "images" / name).is_file()


def test_a_sweep_split_over_sessions_is_marked_in_progress_until_every_run_finished(tmp_path, monkeypatch):
    import results_table

    def summary(key: str, completed: bool) -> None:
        env, condition, seed = key.split("/")
        run = tmp_path / "sweep" / "runs" / env / condition / f"seed-{seed}"
        run.mkdir(parents=True, exist_ok=True)
        (run / "summary.json").write_text(f'{{"completed": {str(completed).lower()}, "env_steps": 1000}}')

    monkeypatch.setattr(results_table, "RESULTS", tmp_path)
    keys = ["Walker2d-v5/none/0", "Walker2d-v5/none/1", "Walker2d-v5/paper/0"]
    record = {"identity": {"runs": {k: {} for k in keys}}}
    summary(keys[0], True)
    summary(keys[1], False)  # stopped with a checkpoint; keys[2] never started
    assert results_table._progress("sweep", record, 1000) == "; **in progress: 1 of 3 runs finished**"
    summary(keys[1], True)
    summary(keys[2], True)
    assert results_table._progress("sweep", record, 1000) == ""


def test_the_site_navigation_says_in_progress_exactly_while_a_sweep_is_unfinished():
    """A report's nav label in mkdocs.yml carries "(in progress)" while, and only while, runs are missing."""
    import json
    import re

    import results_table

    checked = 0
    for line in (ROOT / "mkdocs.yml").read_text().splitlines():
        entry = re.match(r'\s*- "?(.+?)"?: results/(.+)/report\.md$', line)
        if entry is None or not (ROOT / "docs" / "results" / entry[2] / "experiment.json").is_file():
            continue
        record = json.loads((ROOT / "docs" / "results" / entry[2] / "experiment.json").read_text())
        env = next(iter(record["identity"]["runs"])).split("/")[0]
        unfinished = results_table._unfinished(env, entry[2], record)
        assert ("(in progress)" in entry[1]) == bool(unfinished), f"{entry[2]}: label {entry[1]!r}, {unfinished!r}"
        checked += 1
    assert checked >= 40


def test_the_evidence_script_refuses_an_env_without_a_design_before_any_work():
    import subprocess

    done = subprocess.run(["bash", str(ROOT / "benchmarks" / "evidence.sh"), "CartPole-v1"],
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [
        "evidence.sh: CartPole-v1: no evidence design (expected one of the paper's four v5 envs)"
    ]
    assert done.stdout == ""


def test_published_records_name_no_writers_absolute_path():
    """config.toml and experiment.json name their sources relative to the data folders (issue 33)."""
    import json
    import re

    absolute = re.compile(r'^(?:source|recipe_source) = "/', re.M)
    for config in (ROOT / "docs" / "results").rglob("config.toml"):
        assert not absolute.search(config.read_text()), config
    for record in (ROOT / "docs" / "results").rglob("experiment.json"):
        recipes = json.loads(record.read_text()).get("recipes", {})
        assert not any(str(v).startswith("/") for v in recipes.values()), record


def test_a_run_names_its_coach_and_recipe_by_their_place_in_the_data_folders(tmp_path):
    from pidlab.data import portable_name, tuning_dir
    from pidlab.rl.recipe import default_recipe_path, load_recipe
    from pidlab.rl.rundir import config_dict

    shipped = tuning_dir() / "Hopper-v5.paper.toml"
    assert portable_name(shipped) == "tuning/Hopper-v5.paper.toml"
    assert portable_name(tmp_path / "elsewhere" / "mine.toml") == "mine.toml"
    assert portable_name("") == ""
    recipe = load_recipe(default_recipe_path("Hopper-v5"))
    from pidlab.controller.spec import load_spec

    config = config_dict(recipe, load_spec(shipped), str(shipped))
    assert config["coach"]["source"] == "tuning/Hopper-v5.paper.toml"
    assert config["recipe_source"] == "coach/Hopper-v5.toml"


def test_the_aim_is_read_from_the_savings_interval():
    import results_table

    def row(value: float, low: float, high: float) -> dict[str, str]:
        return {"saving": str(value), "saving_low": str(low), "saving_high": str(high)}

    assert "**met**" in results_table.aim_text(row(0.97, 0.92, 1.0), 0.9)
    assert "**missed**" in results_table.aim_text(row(0.3, -0.1, 0.49), 0.5)
    assert "**undecided**" in results_table.aim_text(row(0.6, 0.4, 0.8), 0.5)
    assert "**met**" in results_table.aim_text(row(1.0, 1.0, 1.0), 0.9)  # every coupled run: no fall
    assert results_table.aim_text({"saving": ""}, 0.9).startswith("no saving")


def test_every_coupling_is_read_against_the_best_plain_baseline_once(tmp_path, monkeypatch):
    """Savings against the baseline's own runs, by hand; a copied condition is shown once."""
    import json

    import results_table

    def sweep(name: str, seeds: list[int], rows: list[tuple[str, float, float]]) -> None:
        folder = tmp_path / name
        folder.mkdir()
        (folder / "summary.csv").write_text("env,condition,metric\n")
        conditions = list(dict.fromkeys(c for c, _, _ in rows))
        ident = {"conditions": conditions, "seeds": seeds, "runs": {}}
        (folder / "experiment.json").write_text(json.dumps({"identity": ident}))
        lines = ["env,condition,seed,falls,env_steps_to_alone_target,final_score"]
        lines += [f"Foo-v5,{c},{i},{f},{'' if s == math.inf else s},1.0" for i, (c, f, s) in enumerate(rows)]
        (folder / "metrics.csv").write_text("\n".join(lines) + "\n")

    monkeypatch.setattr(results_table, "RESULTS", tmp_path)
    monkeypatch.setattr(results_table, "_budget", lambda env, name, record: 1000)
    monkeypatch.setattr(results_table, "TEACH_SWEEPS", ("teach", "full"))
    sweep("Foo-v5-sac", [0, 1, 2], [("none-sac", 100, 20000)] * 3)
    fast = [("fast", 0, 10000)] * 3
    sweep("Foo-v5-teach", [0, 1, 2], [("none", 90, 90000)] * 3 + fast + [("stuck", 5, math.inf)] * 3)
    sweep("Foo-v5-full", [0, 1, 2], fast)  # the same runs, copied (Amendment 6)
    assert results_table.named_baseline("Foo-v5") == ("Foo-v5-sac", "none-sac")
    rows = results_table._best_rows("Foo-v5", ("Foo-v5-sac", "none-sac"))
    assert len(rows) == 2 and "| teach | fast |" in rows[0] and "| teach | stuck |" in rows[1]
    # falls 0 against 100: +100 %; env steps 10,000 against 20,000: +50 %, on the aim exactly
    assert "saving +100.0 % [+100.0 %, +100.0 %]: **met** (aim 90 %)" in rows[0]
    assert "saving +50.0 % [+50.0 %, +50.0 %]: **met** (aim 50 %) | **met** |" in rows[0]
    # falls 5 against 100: +95 %; never at the target: the env-steps aim, and so both, missed
    assert "saving +95.0 % [+95.0 %, +95.0 %]: **met**" in rows[1]
    assert rows[1].endswith("**missed** (aim 50 %) | **missed** |")
    assert results_table.named_baseline("Bar-v5") == "not named: plain SAC not run (no amendment governs it)"


def test_a_coupling_at_another_budget_than_the_baselines_is_not_compared(tmp_path, monkeypatch):
    """Falls and env steps to a kept target grow with the budget: a sweep at another one is named, not read."""
    import json

    import results_table

    for name, condition in (("Foo-v5-sac", "none-sac"), ("Foo-v5-teach", "fast")):
        folder = tmp_path / name
        folder.mkdir()
        (folder / "summary.csv").write_text("env,condition,metric\n")
        ident = {"conditions": [condition], "seeds": [0], "runs": {}}
        (folder / "experiment.json").write_text(json.dumps({"identity": ident}))
        lines = ["env,condition,seed,falls,env_steps_to_alone_target,final_score", f"Foo-v5,{condition},0,9,500,1.0"]
        (folder / "metrics.csv").write_text("\n".join(lines) + "\n")
    budgets = {"Foo-v5-sac": 300_000, "Foo-v5-teach": 1_000_000}
    monkeypatch.setattr(results_table, "RESULTS", tmp_path)
    monkeypatch.setattr(results_table, "_budget", lambda env, name, record: budgets[name])
    monkeypatch.setattr(results_table, "_unfinished", lambda env, name, record: "")
    monkeypatch.setattr(results_table, "TEACH_SWEEPS", ("teach",))
    assert results_table._best_rows("Foo-v5", ("Foo-v5-sac", "none-sac")) == [
        "| Foo-v5 | none-sac (SAC, 1 runs) | teach | all | not compared: its runs' budget is 1,000,000 env "
        "steps, the baseline's 300,000 | - | - |"
    ]


def test_the_baseline_is_plain_ppo_else_plain_sac_by_hand():
    from pidlab.experiment.analysis import baseline_of

    assert baseline_of(["none", "none-sac", "rescue-replay"]) == "none"
    assert baseline_of(["none-sac", "rescue-replay"]) == "none-sac"
    assert baseline_of(["rescue-replay", "none-sac"]) == "none-sac"
    assert baseline_of(["rescue-replay"]) == "none"  # no plain learner: nothing is compared


def test_a_sweep_without_plain_ppo_tests_its_couplings_against_plain_sac(tmp_path):
    """Amendment 23: the published runs of rescue-replay read against none-sac's, measure by measure."""
    import shutil

    from pidlab.experiment.analysis import analyze, censored_values, recipes_of_runs
    from pidlab.experiment.stats import median_saving
    from pidlab.report.experiment import report_texts

    env, results = "InvertedPendulum-v5", ROOT / "docs" / "results"
    for cond, sweep in (("none-sac", "sac"), ("rescue-replay", "offpolicy")):
        shutil.copytree(results / f"{env}-{sweep}" / "runs" / env / cond, tmp_path / "runs" / env / cond)
    ident = {"envs": [env], "conditions": ["none-sac", "rescue-replay"], "seeds": list(range(100, 110))}
    a = analyze(ident, tmp_path, recipes_of_runs(tmp_path, ident), reps=200)
    assert a.baseline == "none-sac" and set(a.comparisons) == {(env, "rescue-replay")}
    falls = a.comparisons[(env, "rescue-replay")]["falls"]
    x, _ = censored_values(a.cells[(env, "rescue-replay")].runs, "falls")
    y, _ = censored_values(a.cells[(env, "none-sac")].runs, "falls")
    assert y.min() > 0 and x.max() == 0  # plain SAC falls in its warm-up; behind the shield no run does
    assert falls.saving.value == median_saving(x, y, reps=10).value == 1.0
    report = report_texts(a, {"identity": ident, "command": ["pidlab", "experiment"]}, {env: {}})["report.md"]
    assert "No coach here is `none-sac`" in report and "**rescue-replay** vs no coach" in report


@pytest.mark.parametrize("mode", ["--teach", "--teach2", "--teach3"])
def test_the_teaching_sweeps_refuse_an_env_without_a_design(mode):
    import subprocess

    done = subprocess.run(["bash", str(ROOT / "benchmarks" / "evidence.sh"), mode, "CartPole-v1"],
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [
        "evidence.sh: CartPole-v1: no teaching design (expected one of the paper's four v5 envs)"
    ]


@pytest.mark.parametrize("env", ["Humanoid-v5", "CartPole-v1"])
def test_the_sac_sweep_is_for_the_envs_an_amendment_governs(env):
    """Amendments 8, 18 and 22 govern plain SAC on the paper's envs; others are refused before any work."""
    import subprocess

    done = subprocess.run(["bash", str(ROOT / "benchmarks" / "evidence.sh"), "--sac", env],
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.strip().splitlines() == [
        f"evidence.sh: --sac {env}: the design is for the paper's four v5 envs "
        "(docs/analysis-plan.md, Amendments 8, 18 and 22)"
    ]


def test_the_teaching_table_reads_the_aim_against_the_sweeps_own_baseline():
    """In a sweep without plain PPO, plain SAC is the baseline row (no aim) and the couplings carry the aim."""
    import results_table

    def row(cond: str, metric: str, saving: str = "") -> dict[str, str]:
        cells = {"iqm": "10", "ci_low": "5", "ci_high": "20", "metric": metric, "reached": "10", "runs": "10",
                 "saving": saving, "saving_low": saving, "saving_high": saving, "verdict": ""}  # fmt: skip
        return {"condition": cond, **cells}

    rows = {}
    for cond, saving in (("none-sac", ""), ("demo-replay-short", "0.95")):
        for metric in ("falls", "env_steps_to_alone_target", "final_score"):
            rows[(cond, metric)] = row(cond, metric, saving if metric != "final_score" else "")
    base = results_table.baseline_of(["none-sac", "demo-replay-short"])
    plain = results_table._teach_row("Foo-v5", "offpolicy", "none-sac", rows, base)
    coupled = results_table._teach_row("Foo-v5", "offpolicy", "demo-replay-short", rows, base)
    assert "saving" not in plain and "aim" not in plain  # with none as the baseline: "no saving (...)"
    assert coupled.count("saving +95.0 % [+95.0 %, +95.0 %]: **met**") == 2


def test_the_offpolicy_sweeps_refuse_an_env_outside_the_paper():
    """Amendments 13, 23, 24 and 25 govern SAC's couplings on the four envs; another is refused at once."""
    import subprocess

    done = subprocess.run(["bash", str(ROOT / "benchmarks" / "evidence.sh"), "--offpolicy", "Ant-v5"],
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.strip().splitlines() == [
        "evidence.sh: --offpolicy Ant-v5: the design is for the paper's four v5 envs "
        "(docs/analysis-plan.md, Amendments 13, 23, 24 and 25)"
    ]


def test_an_offpolicy_sweep_without_the_plain_sac_runs_it_copies_is_refused(tmp_path):
    """Amendments 23-25 copy none-sac from the env's finished --sac sweep; short of it the script stops at once."""
    import shutil
    import subprocess

    (tmp_path / "benchmarks").mkdir()
    shutil.copy(ROOT / "benchmarks" / "evidence.sh", tmp_path / "benchmarks" / "evidence.sh")
    script = ["bash", str(tmp_path / "benchmarks" / "evidence.sh"), "--offpolicy", "Hopper-v5"]

    def refusal(missing: int) -> list[str]:
        return [
            "evidence.sh: --offpolicy Hopper-v5 copies its plain SAC runs (none-sac, seeds 100-109) from the --sac "
            f"sweep, and {missing} of the 10 are not finished in results/Hopper-v5-sac or docs/results/Hopper-v5-sac; "
            "run bash benchmarks/evidence.sh --sac Hopper-v5 first"
        ]

    def finish(place: str, seeds: range, completed: str = "true") -> None:
        for seed in seeds:
            run = tmp_path / place / "Hopper-v5-sac" / "runs" / "Hopper-v5" / "none-sac" / f"seed-{seed}"
            run.mkdir(parents=True, exist_ok=True)
            (run / "summary.json").write_text(f'{{\n  "completed": {completed},\n  "env_steps": 5\n}}\n')

    done = subprocess.run(script, capture_output=True, text=True, timeout=60)
    assert (done.returncode, done.stdout, done.stderr.strip().splitlines()) == (2, "", refusal(10))
    finish("docs/results", range(100, 106))  # a sweep stopped part-way: its checkpointed runs say so
    finish("results", range(106, 109), completed="false")
    for place in ("results", "docs/results"):  # each sweep folder holds its experiment.json from the start
        (tmp_path / place / "Hopper-v5-sac" / "experiment.json").write_text("{}")
    done = subprocess.run(script, capture_output=True, text=True, timeout=60)
    assert (done.returncode, done.stdout, done.stderr.strip().splitlines()) == (2, "", refusal(4))
    finish("results", range(106, 110))  # finished here, the rest published: every one is there
    done = subprocess.run(script, capture_output=True, text=True, timeout=60)  # past the check: no setup here
    assert "copies its plain SAC runs" not in done.stderr and "scripts/setup.sh" in done.stderr
    ip = ["bash", str(tmp_path / "benchmarks" / "evidence.sh"), "--offpolicy", "InvertedPendulum-v5"]
    done = subprocess.run(ip, capture_output=True, text=True, timeout=60)  # its sweep holds plain PPO
    assert "copies its plain SAC runs" not in done.stderr and "scripts/setup.sh" in done.stderr


@pytest.mark.parametrize(
    ("sweep", "amendment", "home", "env"),
    [("edgemodel", 14, "InvertedPendulum-v5", "Hopper-v5"),
     ("learned", 15, "InvertedDoublePendulum-v5", "InvertedPendulum-v5"),
     ("room", 16, "Hopper-v5", "Walker2d-v5"), ("teach7", 10, "InvertedDoublePendulum-v5", "Hopper-v5"),
     ("teach8", 19, "InvertedDoublePendulum-v5", "InvertedPendulum-v5"), ("roomfocus", 20, "Hopper-v5", "Walker2d-v5"),
     ("roommodel", 21, "Hopper-v5", "InvertedPendulum-v5")],
)  # fmt: skip
def test_the_one_env_sweeps_refuse_other_envs(env, sweep, amendment, home):
    """Amendments 10, 13 to 16 and 19 to 21 govern their couplings on one env each; other envs are refused at once."""
    import subprocess

    done = subprocess.run(["bash", str(ROOT / "benchmarks" / "evidence.sh"), f"--{sweep}", env],
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.strip().splitlines() == [
        f"evidence.sh: --{sweep} {env}: the design is for {home} (docs/analysis-plan.md, Amendment {amendment})"
    ]


def test_the_status_of_a_sweep_trains_restores_and_publishes_nothing(tmp_path):
    """``evidence.sh DESIGN ENV -- --status`` says how far the sweep is, from the published runs when
    results/ has none here, and writes nothing: no restore, no training, no publishing."""
    import subprocess

    for folder in ("benchmarks", "scripts", ".venv/bin"):
        (tmp_path / folder).mkdir(parents=True)
    (tmp_path / "benchmarks" / "evidence.sh").write_bytes((ROOT / "benchmarks" / "evidence.sh").read_bytes())
    (tmp_path / "scripts" / "setup.sh").write_text("")  # installed already: this venv's pidlab
    (tmp_path / ".venv" / "bin" / "pidlab").symlink_to(Path(sys.executable).with_name("pidlab"))
    for shipped in ("coach", "tuning", "models", "docs"):
        (tmp_path / shipped).symlink_to(ROOT / shipped)
    published = ROOT / "docs" / "results" / "InvertedPendulum-v5-offpolicy"
    before = sorted((str(p), p.stat().st_mtime_ns) for p in published.rglob("*"))
    script = ["bash", str(tmp_path / "benchmarks" / "evidence.sh"), "--offpolicy", "InvertedPendulum-v5"]
    done = subprocess.run([*script, "--", "--status"], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[0] == f"experiment {published.resolve()}"
    assert lines[-1] == (
        "runs: 50 finished, 0 under way, 0 not started, 0 damaged (of 50); 2,500,000 of 2,500,000 env steps "
        "checkpointed (100.0 %)"
    )
    assert not (tmp_path / "results").exists()
    assert sorted((str(p), p.stat().st_mtime_ns) for p in published.rglob("*")) == before
