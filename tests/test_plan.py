"""The analysis plan: the document, the code that applies it and the sweeps that run it agree."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

from pidlab.experiment import plan
from pidlab.rl.recipe import default_recipe_path, load_recipe

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / plan.PLAN_FILE


def _number(text: str) -> int:
    return int(text.replace(",", ""))


def _table_rows(heading: str) -> list[list[str]]:
    """The rows of the first Markdown table after ``heading`` in the plan."""
    text = DOC.read_text()
    section = text[text.index(heading) :]
    rows = []
    for line in section.splitlines()[1:]:
        if line.startswith("|"):
            rows.append([c.strip().strip("*") for c in line.strip("|").split("|")])
        elif rows:
            break
    return rows[2:]  # header and rule


def test_the_design_table_is_the_codes_and_the_recipes():
    rows = _table_rows("## 2. Design")
    assert [r[0] for r in rows] == list(plan.BUDGETS)
    for env, budget, every, episodes in rows:
        assert _number(budget) == plan.BUDGETS[env]
        assert (
            _number(every)
            == plan.EVALUATION_EVERY[env]
            == load_recipe(default_recipe_path(env)).evaluation.every
        )
        assert _number(episodes) == load_recipe(default_recipe_path(env)).evaluation.episodes


def test_the_targets_table_is_the_codes():
    for env, paper, alone, _ in _table_rows("## 3. Targets"):
        win = load_recipe(default_recipe_path(env)).win.target
        assert _number(paper) == win
        assert _number(alone) == plan.ALONE_TARGETS.get(env, win)
        assert (plan.alone_target(env, win) is None) == (env not in plan.ALONE_TARGETS)


def test_the_confirmatory_sweeps_are_the_plans():
    script = (ROOT / "benchmarks" / "evidence.sh").read_text()
    body = script[script.index("confirm_design() {") :]
    budgets = dict(re.findall(r"^\s+([\w-]+)\) steps=(\d+) ;;", body, re.M))
    assert {env: int(v) for env, v in budgets.items()} == plan.BUDGETS
    conditions, seeds = re.search(r'echo "\$1-confirm ([\w,-]+) \$steps (\d+-\d+)"', body).groups()
    assert tuple(conditions.split(",")) == plan.CONFIRMATORY_CONDITIONS
    low, high = map(int, seeds.split("-"))
    assert tuple(range(low, high + 1)) == plan.CONFIRMATORY_SEEDS
    assert "Seeds**: 100-109" in DOC.read_text()


def test_a_condition_no_part_of_the_plan_governs_makes_a_sweep_exploratory():
    conditions = ["none", "rescue-terminal", "rescue-terminal-model"]
    assert plan.ungoverned(conditions) == ("rescue-terminal-model",)
    assert plan.role(range(100, 110), conditions) == "exploratory"
    cited = plan.citation(range(100, 110), conditions)
    assert "**Exploratory sweep**: neither the plan nor an amendment governs rescue-terminal-model" in cited
    assert "Confirmatory" not in cited
    assert plan.role(range(100, 110), ["none", "rescue-terminal", "warm-start"]) == "confirmatory"
    assert plan.role(range(10), conditions) == "pilot"  # a pilot stays a pilot


def test_a_sweep_of_another_agent_than_the_plans_is_exploratory():
    assert plan.role(range(100, 110), ["none", "paper"], ["sac"]) == "exploratory"
    assert plan.role(range(100, 110), ["none", "paper"], ["ppo"]) == "confirmatory"
    cited = plan.citation(range(100, 110), ["none"], ["sac"])
    assert "governs the agent SAC in this sweep" in cited and "Confirmatory" not in cited


def test_amendments_8_18_and_22_govern_plain_sac_on_the_papers_envs():
    sweep, algos = ["none", "none-sac"], ["ppo", "sac"]
    owners = {"InvertedPendulum-v5": 8, "InvertedDoublePendulum-v5": 8, "Hopper-v5": 18, "Walker2d-v5": 22}
    for env, k in owners.items():
        assert plan.role(range(100, 110), sweep, algos, [env]) == "confirmatory"
        assert plan.amendments_of(sweep, [env], range(100, 110)) == (k,)
    assert "Amendment 8" not in plan.citation(range(100, 110), sweep, algos, ["Walker2d-v5"])
    assert plan.role(range(110, 120), sweep, algos, ["Walker2d-v5"]) == "pilot"  # not its seeds
    assert plan.ungoverned(sweep, ["Walker2d-v5"], range(100, 110)) == ()
    # SAC is governed only with the condition that names it
    assert plan.unplanned_algorithms(["ppo", "sac"], ["none", "paper"]) == ("sac",)
    assert plan.unplanned_algorithms(["ppo", "sac"], sweep, ["InvertedPendulum-v5"]) == ()
    assert plan.role(range(10), sweep, algos, ["InvertedPendulum-v5"]) == "pilot"


def test_amendment_13_governs_the_off_policy_couplings_on_invertedpendulum_only():
    sweep = ["none", "rescue-replay", "rescue-value", "rescue-propose", "warm-start-keep-shield-short"]
    ip, idp = ["InvertedPendulum-v5"], ["InvertedDoublePendulum-v5"]
    assert plan.role(range(100, 110), sweep, ["ppo", "sac"], ip) == "confirmatory"
    assert plan.amendments_of(sweep, ip, range(100, 110)) == (13,)
    assert "Amendment 13" in plan.citation(range(100, 110), sweep, ["ppo", "sac"], ip)
    assert plan.role(range(100, 110), sweep, ["ppo", "sac"], idp) == "exploratory"
    # Amendment 23 governs rescue-replay there, not the other two
    assert plan.ungoverned(sweep, idp) == ("rescue-value", "rescue-propose", "warm-start-keep-shield-short")
    # its PPO comparator keeps Amendment 4's seeds too; 13 governs it on InvertedPendulum's 100-109
    assert plan.amendments_of(["warm-start-keep-shield-short"], ip, range(110, 120)) == (4,)


def test_amendment_23_governs_two_sac_couplings_on_the_double_pendulum_against_plain_sac():
    sweep, idp = ["none-sac", "rescue-replay", "demo-replay-short"], ["InvertedDoublePendulum-v5"]
    assert plan.role(range(100, 110), sweep, ["sac"], idp) == "confirmatory"
    assert plan.amendments_of(sweep, idp, range(100, 110)) == (8, 23)
    assert "Amendment 23" in plan.citation(range(100, 110), sweep, ["sac"], idp)
    for env in ("InvertedPendulum-v5", "Hopper-v5", "Walker2d-v5"):
        assert "demo-replay-short" in plan.ungoverned(sweep, [env])


def test_amendment_24_governs_the_room_shields_sac_coupling_on_hopper_against_plain_sac():
    sweep, hopper = ["none-sac", "rescue-replay-room"], ["Hopper-v5"]
    assert plan.role(range(100, 110), sweep, ["sac"], hopper) == "confirmatory"
    assert plan.amendments_of(sweep, hopper, range(100, 110)) == (18, 24)
    assert plan.role(range(100, 110), sweep, ["sac"], ["Walker2d-v5"]) == "exploratory"


def test_amendment_25_governs_the_balance_coachs_demonstrations_on_walker2d_against_plain_sac():
    sweep, walker = ["none-sac", "demo-replay-balance"], ["Walker2d-v5"]
    assert plan.role(range(100, 110), sweep, ["sac"], walker) == "confirmatory"
    assert plan.amendments_of(sweep, walker, range(100, 110)) == (22, 25)
    assert "Amendment 25" in plan.citation(range(100, 110), sweep, ["sac"], walker)
    assert plan.role(range(100, 110), sweep, ["sac"], ["Hopper-v5"]) == "exploratory"


def test_an_amendment_governs_only_its_envs_and_seeds():
    short, hopper = ["none", "warm-start-keep-shield-short"], ["Hopper-v5"]
    idp = ["InvertedDoublePendulum-v5"]
    # Amendment 7: Hopper and Walker2d on the plan's seeds; Amendment 4: every env on 110-119
    assert plan.role(range(100, 110), short, envs=hopper) == "confirmatory"
    assert plan.amendments_of(short, hopper, range(100, 110)) == (7,)
    assert "Amendment 7" in plan.citation(range(100, 110), short, envs=hopper)
    assert "Amendment 4" not in plan.citation(range(100, 110), short, envs=hopper)
    assert plan.role(range(110, 120), short, envs=hopper) == "confirmatory"
    assert plan.amendments_of(short, hopper, range(110, 120)) == (4,)
    assert plan.role(range(100, 110), short, envs=idp) == "exploratory"
    assert plan.ungoverned(short, idp) == ("warm-start-keep-shield-short",)
    assert plan.role(range(110, 120), short, envs=idp) == "confirmatory"
    # a sweep over both kinds of env is confirmatory only where every env is governed
    assert plan.role(range(100, 110), short, envs=[*hopper, *idp]) == "exploratory"
    assert plan.fresh_seed_sets(short, hopper) == (tuple(range(100, 110)), tuple(range(110, 120)))
    assert "100-109 or 110-119" in plan.citation(range(5), short, envs=hopper)


def test_roles_and_citation():
    assert plan.role(range(100, 110)) == "confirmatory"
    assert plan.role(range(10)) == "pilot" and plan.role(range(100, 105)) == "pilot"
    assert plan.PLAN_COMMIT[:7] in plan.citation(range(100, 110)) and "Confirmatory" in plan.citation(
        range(100, 110)
    )
    assert "Pilot" in plan.citation(range(3))


def _git(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, check=False)


def test_the_plan_was_committed_before_and_only_amended_since():
    try:
        shallow = _git("rev-parse", "--is-shallow-repository")
    except OSError:
        pytest.skip("git is not installed")
    if shallow.returncode != 0:
        pytest.skip("not a git checkout")
    if shallow.stdout.strip() == "true":
        pytest.skip("a shallow clone has no history to check the plan's commit in")
    committed = _git("show", f"{plan.PLAN_COMMIT}:{plan.PLAN_FILE}")
    assert committed.returncode == 0, f"the plan's commit {plan.PLAN_COMMIT} does not hold {plan.PLAN_FILE}"
    # the commit introduced the plan
    assert _git("cat-file", "-e", f"{plan.PLAN_COMMIT}^:{plan.PLAN_FILE}").returncode != 0
    # everything above the amendments is as committed; amendments are only appended
    head = "## Amendments"
    then, now = committed.stdout, DOC.read_text()
    assert now[: now.index(head)] == then[: then.index(head)]
    assert now.startswith(then[: then.index(head) + len(head)])


def test_every_condition_an_amendment_governs_is_named_in_its_amendment():
    text = (ROOT / plan.PLAN_FILE).read_text()
    amendments = text[text.index("## Amendments") :]
    for amendment in plan.AMENDMENT_LIST:
        k = amendment.number
        section = amendments[amendments.index(f"### Amendment {k} ") :]
        following = section.find("### Amendment", 5)
        section = section if following < 0 else section[:following]
        for condition in amendment.conditions:
            assert f"`{condition}`" in section, (condition, k)
        for env in amendment.envs if amendment.envs != plan.PAPER_ENVS else ():
            assert env.split("-")[0] in section, (env, k)
        for algo in amendment.algorithms:
            assert algo == "ppo" or algo.upper() in section, (algo, k)
        if amendment.seeds != plan.CONFIRMATORY_SEEDS:
            assert f"{amendment.seeds[0]}-{amendment.seeds[-1]}" in section, k
    cited = plan.citation(range(100, 110), ["none", "rescue-terminal", "rollin", "warm-start"])
    assert "Amendment 1 and Amendment 2" in cited and "Confirmatory" in cited
    assert "Amendment" not in plan.citation(range(100, 110), ["none", "paper", "rescue-terminal"])
    # Amendment 4 confirms on its own fresh seeds
    short = ["none", "warm-start-keep-shield-short"]
    assert plan.role(range(110, 120), short) == "confirmatory"
    assert plan.role(range(100, 110), short, envs=["InvertedDoublePendulum-v5"]) == "exploratory"
    assert plan.role(range(120, 130), short) == "pilot"
    assert "seeds 110-119" in plan.citation(range(110, 120), short)
    # Amendment 19 confirms on its own fresh seeds, on InvertedDoublePendulum only
    held, idp = ["none", "warm-start-hold-short"], ["InvertedDoublePendulum-v5"]
    assert plan.role(range(120, 130), held, envs=idp) == "confirmatory"
    assert plan.role(range(120, 130), held, envs=["Hopper-v5"]) == "pilot"
    assert plan.role(range(110, 120), held, envs=idp) == "pilot"


def test_the_runs_say_which_agents_a_sweep_trained(tmp_path):
    from pidlab.experiment.analysis import run_algorithms

    env = "InvertedPendulum-v5"
    for condition, text in (("none", 'algo = "ppo"'), ("none-sac", 'algo = "sac"'), ("broken", "algo = ")):
        run = tmp_path / "runs" / env / condition / "seed-100"
        run.mkdir(parents=True)
        (run / "config.toml").write_text(f"[recipe]\n{text}\n")
    assert run_algorithms(tmp_path, [env], ["none", "none-sac", "broken"]) == ("ppo", "sac")
    assert run_algorithms(tmp_path, [env], ["none"]) == ("ppo",)
    assert run_algorithms(tmp_path, [env], ["missing"]) == ()
    sweep = ["none", "none-sac"]
    assert plan.role(range(100, 110), sweep, run_algorithms(tmp_path, [env], sweep), [env]) == "confirmatory"
    shield = tmp_path / "runs" / env / "rescue-terminal" / "seed-100"
    shield.mkdir(parents=True)
    (shield / "config.toml").write_text('[recipe]\nalgo = "sac"\n')  # no amendment governs SAC with it
    sweep = ["none", "rescue-terminal"]
    assert plan.role(range(100, 110), sweep, run_algorithms(tmp_path, [env], sweep), [env]) == "exploratory"


def test_the_best_plain_baseline_follows_amendment_8_by_hand():
    """Smaller median env steps (never reached = inf); then the larger median final score; then none."""
    inf = float("inf")
    ppo = plan.PlainLearner("none", (10_000.0, 12_500.0, 7_500.0), (1000.0, 1000.0, 1000.0))
    sac = plan.PlainLearner("none-sac", (15_000.0, 17_500.0, 5_000.0), (1000.0, 1000.0, 1000.0))
    assert plan.best_plain_baseline([sac, ppo]) is ppo  # medians 10,000 against 15,000
    fast = plan.PlainLearner("none-sac", (inf, 2_500.0, 5_000.0, inf, 2_500.0), (1.0,) * 5)
    assert plan.best_plain_baseline([ppo, fast]) is fast  # median 5,000 (two never reached) against 10,000
    never = plan.PlainLearner("none-sac", (inf, inf, 5_000.0), (1000.0,) * 3)
    assert plan.best_plain_baseline([ppo, never]) is ppo  # median inf
    even = plan.PlainLearner("none-sac", (5_000.0, 15_000.0), (900.0, 1000.0))  # median 10,000 (mean of two)
    assert plan.best_plain_baseline([even, ppo]) is ppo  # tie on steps: final 1000 against 950
    same = plan.PlainLearner("none-sac", (12_500.0, 7_500.0, 10_000.0), (1000.0, 1000.0, 1000.0))
    assert plan.best_plain_baseline([same, ppo]) is ppo  # a full tie goes to none
    both_never = plan.PlainLearner("none", (inf, inf), (5.0, 7.0))
    sac_never = plan.PlainLearner("none-sac", (inf, inf), (6.0, 9.0))
    assert plan.best_plain_baseline([both_never, sac_never]) is sac_never  # inf = inf: final 7.5 against 6
    with pytest.raises(ValueError, match="at least one learner"):
        plan.best_plain_baseline([])
