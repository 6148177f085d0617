"""Learning-speed metrics and rliable-style statistics on hand-made curves with known answers."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from pidlab.experiment.metrics import (
    Rule,
    RunLogs,
    episodes_to_average,
    episodes_to_consecutive_wins,
    first_hit,
    first_reaching,
    grid_points,
    moving_average,
    run_metrics,
    sustained_hit,
)
from pidlab.experiment.stats import bootstrap_ci, iqm, probability_of_improvement


def test_five_wins_point_is_the_fifth_win_of_the_first_streak():
    # wins at 3..6 (four), a loss at 7, then wins 8..12: the fifth in a row is episode 12
    returns = [0, 0, 900, 900, 900, 900, 10, 800, 801, 999, 1000, 850, 900]
    assert episodes_to_consecutive_wins(returns, 800, 5) == 12
    assert episodes_to_consecutive_wins(returns, 800, 4) == 6
    assert episodes_to_consecutive_wins(returns, 1001, 1) is None
    assert episodes_to_consecutive_wins([], 800, 5) is None


def test_target_counts_as_a_win_exactly_at_the_threshold():
    assert episodes_to_consecutive_wins([800.0] * 5, 800, 5) == 5
    assert episodes_to_consecutive_wins([799.999] * 5, 800, 5) is None


def test_moving_average_needs_a_full_window():
    # one lucky early episode must not count: the average of a short first window is not used
    returns = [1000, 0, 0, 0, 1000, 1000, 1000, 1000]
    assert episodes_to_average(returns, 800, 4) == 8  # mean(1000 x 4) at episode 8
    assert episodes_to_average(returns, 500, 4) == 6  # mean(0, 0, 1000, 1000) = 500 at episode 6
    assert episodes_to_average(returns[:3], 0, 4) is None
    np.testing.assert_allclose(moving_average([2, 4, 6, 8], 2), [2, 3, 5, 7])


def test_linear_ramp_crosses_the_average_where_arithmetic_says():
    returns = np.arange(1, 201) * 10.0  # episode k scores 10 k
    # mean of episodes k-19..k = 10 (k - 9.5) >= 800  <=>  k >= 89.5
    assert episodes_to_average(returns, 800, 20) == 90
    assert episodes_to_consecutive_wins(returns, 800, 5) == 84  # 80..84


def logs(returns, ev_env, ev_agent, means, env_steps, agent_steps, coach_steps, coached=None, updates=100):
    """RunLogs from plain lists (evaluations of 10 episodes of 1000 steps)."""
    returns = np.asarray(returns, dtype=float)
    n = len(returns)
    return RunLogs(
        returns=returns,
        coached_returns=returns if coached is None else np.asarray(coached, dtype=float),
        episode_env_steps=np.linspace(env_steps / max(n, 1), env_steps, n),
        episode_coach_steps=np.full(n, coach_steps / max(n, 1)),
        eval_env_steps=np.asarray(ev_env, dtype=np.int64),
        eval_agent_steps=np.asarray(ev_agent, dtype=float),
        eval_means=np.asarray(means, dtype=float),
        eval_steps=np.full(len(means), 10000),
        env_steps=env_steps,
        agent_steps=agent_steps,
        coach_steps=coach_steps,
        policy_updates=updates,
    )


RULE = Rule(target=800, consecutive=5, window=20, every=5000, budget=100000)


def test_first_reaching_and_run_metrics_agent_alone():
    ev_env = [0, 5000, 10000, 15000]
    ev_agent = [0, 1000, 2500, 6000]
    means = [20.0, 300.0, 850.0, 1000.0]
    assert first_reaching(ev_env, means, 800) == 10000
    m = run_metrics(logs([900.0] * 30, ev_env, ev_agent, means, 15000, 6000, 9000), RULE)
    assert m.env_steps_to_target == 10000 and m.agent_steps_to_target == 2500
    assert m.episodes_to_wins == 5 and m.episodes_to_average == 20
    assert m.final_score == 1000.0 and m.intervention_rate == pytest.approx(0.6)
    assert not m.coach_dependent and not m.never_trained
    assert m.evaluation_env_steps == 40000 and m.env_steps_per_episode == pytest.approx(500)


def test_coach_dependence_is_good_with_the_coach_and_bad_alone():
    m = run_metrics(logs([950.0] * 40, [0, 5000], [0, 800], [10.0, 40.0], 5000, 800, 4200), RULE)
    assert m.coach_dependent and m.env_steps_to_target is None
    # the agent earns little on its own steps, but with the coach's steps the episodes score 1000
    m = run_metrics(
        logs([100.0] * 40, [0, 5000], [0, 800], [10.0, 40.0], 5000, 800, 4200, [1000.0] * 40), RULE
    )
    assert m.final_training_score == 100.0 and m.final_coached_score == 1000.0 and m.coach_dependent
    # the same curves without a coach in the loop are not "coach dependence"
    m0 = run_metrics(logs([950.0] * 40, [0, 5000], [0, 5000], [10.0, 40.0], 5000, 5000, 0), RULE)
    assert not m0.coach_dependent


def test_a_run_without_a_policy_update_is_never_trained_not_coach_dependent():
    # Walker2d, pidlab: 40 agent steps in 25,000 env steps, less than one PPO rollout of 512
    m = run_metrics(
        logs([1.3] * 30, [0, 25000], [0, 40], [10.0, 12.0], 25000, 40, 24960, [935.0] * 30, updates=0), RULE
    )
    assert m.never_trained and not m.coach_dependent and m.policy_updates == 0
    unknown = run_metrics(
        logs([1.3] * 30, [0, 25000], [0, 40], [10.0, 12.0], 25000, 40, 24960, [935.0] * 30, updates=None),
        RULE,
    )
    assert not unknown.never_trained and unknown.coach_dependent and unknown.policy_updates is None


def test_a_transient_hit_does_not_count_as_reaching_the_target():
    # IP pidlab seed 6: a hit at the first evaluation after 5,000 steps, a final score of 3.9
    means = [5.0, 820.0, 30.0, 900.0, 3.9]
    m = run_metrics(logs([10.0] * 30, [0, 5001, 10000, 15002, 20000], [0, 900, 1800, 2700, 3600], means,
                         20000, 3600, 16400), RULE)  # fmt: skip
    assert m.env_steps_to_target is None and m.agent_steps_to_target is None
    assert m.first_hit_env_steps == 5000 and m.final_score == 3.9
    kept = run_metrics(logs([10.0] * 30, [0, 5001, 10000, 15002, 20000], [0, 900, 1800, 2700, 3600],
                            [5.0, 820.0, 30.0, 900.0, 950.0], 20000, 3600, 16400), RULE)  # fmt: skip
    assert kept.env_steps_to_target == 15000 and kept.agent_steps_to_target == 2700
    assert kept.evaluation_delay == 2


def test_sustained_hit_and_final_score_agree():
    assert sustained_hit([0, 900, 100, 900, 950], 800) == 3
    assert sustained_hit([0, 900, 100], 800) is None
    assert sustained_hit([900, 900], 800) == 0
    assert sustained_hit([], 800) is None
    assert sustained_hit([0, float("nan"), 900], 800) == 2
    assert first_hit([0, 900, 100], 800) == 1 and first_hit([0, 1], 800) is None


def test_evaluations_a_few_steps_late_sit_at_their_grid_point():
    assert grid_points([0, 5000, 10003, 14999, 15000], 5000, 100000).tolist() == [
        0,
        5000,
        10000,
        10000,
        15000,
    ]
    # the final evaluation is due at the budget, also when the budget is off the grid (IDP: 50,000, every 20,000)
    assert grid_points([0, 20000, 40000, 50000, 50004], 20000, 50000).tolist() == [
        0,
        20000,
        40000,
        50000,
        50000,
    ]
    idp = Rule(target=5500, consecutive=5, window=150, every=20000, budget=50000)
    m = run_metrics(logs([10.0] * 5, [0, 20000, 40000, 50000], [0] * 4, [5.0, 100.0, 200.0, 9000.0], 50000, 50000, 0),
                    idp)  # fmt: skip
    assert m.env_steps_to_target == 50000 and m.evaluation_delay == 0
    # a coached run evaluated at 10,003 ties with an uncoached one evaluated at 10,000
    late = run_metrics(logs([10.0] * 5, [0, 5002, 10003], [0, 4000, 8000], [5.0, 100.0, 900.0], 10003, 8000, 2003),
                       RULE)  # fmt: skip
    on_time = run_metrics(logs([10.0] * 5, [0, 5000, 10000], [0, 5000, 10000], [5.0, 100.0, 900.0], 10000, 10000, 0),
                          RULE)  # fmt: skip
    assert late.env_steps_to_target == on_time.env_steps_to_target == 10000


def test_the_return_cap_is_measured_on_both_kinds_of_return():
    # a heavy coach: 900 coach steps per 1000-step episode, so the agent can earn at most 100
    agent, both = [100.0] * 40, [1000.0] * 40
    m = run_metrics(logs(agent, [0, 5000], [0, 500], [10.0, 1000.0], 5000, 500, 4500, both), RULE)
    assert m.episodes_to_wins is None and m.episodes_to_average is None
    assert m.episodes_to_wins_with_coach == 5 and m.episodes_to_average_with_coach == 20


def test_iqm_trims_a_quarter_each_side():
    assert iqm([1, 2, 3, 4, 100, 5, 6, 7]) == pytest.approx(4.5)
    assert iqm([3.0]) == 3.0
    # more than a quarter of the runs never reached: the IQM is "not reached"
    assert math.isinf(iqm([1, 2, np.inf, np.inf]))
    np.testing.assert_allclose(iqm(np.arange(8.0).reshape(2, 4), axis=-1), [1.5, 5.5])


def test_bootstrap_interval_is_deterministic_and_covers_the_estimate():
    rng = np.random.default_rng(0)
    x = rng.normal(10.0, 2.0, 20)
    a = bootstrap_ci([x], reps=1000, seed=3)
    b = bootstrap_ci([x], reps=1000, seed=3)
    assert a == b
    assert a.low < a.value < a.high
    assert a.value == pytest.approx(iqm(x))
    # identical runs: no spread at all
    c = bootstrap_ci([[5.0] * 10], reps=200)
    assert (c.low, c.value, c.high) == (5.0, 5.0, 5.0)


def test_bootstrap_is_stratified_by_task():
    # task 0 always 0, task 1 always 100: every stratified resample keeps one of each per pair,
    # so the mean of a resample is always 50 (an unstratified one would wander)
    e = bootstrap_ci([[0.0, 0.0], [100.0, 100.0]], statistic=np.mean, reps=500)
    assert e.low == e.high == 50.0


def test_probability_of_improvement_known_cases():
    assert probability_of_improvement([[5, 6, 7]], [[1, 2, 3]]).value == 1.0
    assert probability_of_improvement([[1, 2, 3]], [[5, 6, 7]]).value == 0.0
    # ties count half; infinities (never reached) tie with each other
    assert probability_of_improvement([[1.0, np.inf]], [[1.0, np.inf]]).value == 0.5
    # averaged over tasks
    p = probability_of_improvement([[5.0], [0.0]], [[1.0], [1.0]], reps=50)
    assert p.value == 0.5
    # pairs (1,1) tie, (1,3) lose, (2,1) win, (2,3) lose: 1.5 of 4
    assert probability_of_improvement([[1.0, 2.0]], [[1.0, 3.0]]).value == pytest.approx((0.5 + 1) / 4)


def test_falls_and_env_resets_of_old_and_new_run_logs(tmp_path):
    """Runs logged before falls were counted: a terminated episode was a fall, and every episode's end a reset."""
    from pidlab.experiment.analysis import read_logs

    old = "episode,env_steps_so_far,agent_steps_so_far,agent_steps,coach_steps,interventions,agent_return,total_return,terminated,env_index\n"
    rows = [
        f"{i},{100 * (i + 1)},{100 * (i + 1)},100,0,0,100.0,100.0,{int(i % 3 == 0)},{i % 2}\n"
        for i in range(7)
    ]
    (tmp_path / "episodes.csv").write_text(old + "".join(rows))
    (tmp_path / "evaluations.csv").write_text(
        "env_steps_so_far,agent_steps_so_far,episodes_so_far,mean_return,std_return,min_return,max_return,mean_length,returns\n"
        "0,0,0,10.0,0.0,10.0,10.0,10.0,10.0\n"
    )
    (tmp_path / "config.toml").write_text("[recipe]\nn_envs = 2\n")
    summary = {"completed": True, "env_steps": 700, "agent_steps": 700, "coach_steps": 0, "resumes": 1}
    got = read_logs(tmp_path, summary)
    assert got.falls == 3  # episodes 0, 3, 6 ended terminated
    assert got.env_resets == 7 + 2 * 2  # one per episode, and each of 2 envs at each of 2 sessions
    m = run_metrics(got, RULE)
    assert (m.falls, m.env_resets) == (3, 11)
    # a run that counted them says so in summary.json (a terminal-view rescue is not a fall)
    assert read_logs(tmp_path, {**summary, "falls": 1, "env_resets": 4}).falls == 1
    (tmp_path / "config.toml").unlink()
    assert read_logs(tmp_path, summary).env_resets is None  # not derivable without the run's n_envs
    with pytest.raises(ValueError, match="falls = -1"):
        read_logs(tmp_path, {**summary, "falls": -1})


def test_episode_logs_read_by_column_are_the_rows_read_one_by_one(tmp_path):
    """read_logs holds episodes.csv by column: the same numbers as row by row; a ragged row is damage."""
    from pidlab.experiment.analysis import read_logs
    from pidlab.rl.rundir import EPISODE_COLUMNS, csv_columns, read_csv_rows, read_csv_table

    rows = [[str(i), str(10 * (i + 1)), str(10 * (i + 1)), "10", "0", "0", f"{i / 3!r}", f"{i / 7!r}", "0", "0",
             str(i % 2), "0"] for i in range(5)]  # fmt: skip
    columns = EPISODE_COLUMNS[: EPISODE_COLUMNS.index("runs")]  # a log written before roll-ins
    text = ",".join(columns) + "\n" + "".join(",".join(r) + "\n" + ("\n" if i == 2 else "")
                                                      for i, r in enumerate(rows))  # fmt: skip
    (tmp_path / "episodes.csv").write_text(text)
    (tmp_path / "evaluations.csv").write_text(
        "env_steps_so_far,agent_steps_so_far,episodes_so_far,mean_return,std_return,min_return,max_return,mean_length,returns\n"
        "50,50,5,10.0,0.0,10.0,10.0,10.0,10.0\n"
    )
    summary = {"completed": True, "env_steps": 50, "agent_steps": 50, "coach_steps": 0, "falls": 0,
               "env_resets": 5, "episodes": 5}  # fmt: skip
    got = read_logs(tmp_path, summary)
    by_row = read_csv_rows(tmp_path / "episodes.csv")  # the blank line is skipped by both
    assert got.returns.tolist() == [float(r["agent_return"]) for r in by_row] == [i / 3 for i in range(5)]
    assert got.coached_returns.tolist() == [i / 7 for i in range(5)]
    assert got.episode_env_steps.tolist() == [10.0, 20.0, 30.0, 40.0, 50.0]
    assert got.env_episodes_ended.tolist() == [0, 1, 1, 2, 2]
    assert np.isnan(got.episode_runs).all()  # no runs column: not a roll-in's log
    header, kept = read_csv_table(tmp_path / "episodes.csv")
    assert csv_columns(header, kept, "episodes.csv")["episode"] == ("0", "1", "2", "3", "4")
    assert csv_columns(header, [], "x.csv") == {c: () for c in columns}
    assert read_csv_table(tmp_path / "absent.csv") == ([], [])
    # a row with a field too many (or too few) is named, not read shifted or padded
    (tmp_path / "episodes.csv").write_text(text.replace("\n3,", "\n3,99,", 1))
    with pytest.raises(ValueError, match="episodes.csv: row 4 has 13 fields, expected 12"):
        read_logs(tmp_path, summary)
    (tmp_path / "episodes.csv").write_text(text.replace(",0\n", "\n", 1))
    with pytest.raises(ValueError, match="episodes.csv: row 1 has 11 fields, expected 12"):
        read_logs(tmp_path, summary)
    # a missing row is told by the count summary.json records before any field is read
    (tmp_path / "episodes.csv").write_text(text.rsplit("\n", 2)[0][:-3] + "\n")
    with pytest.raises(ValueError, match="episodes.csv holds 4 of the 5 episodes"):
        read_logs(tmp_path, summary)
    (tmp_path / "episodes.csv").write_text(text.replace(",1,0\n", ",2,0\n", 1))
    with pytest.raises(ValueError, match="env_end = '2', expected 0 or 1"):
        read_logs(tmp_path, summary)


def test_the_papers_measures_in_env_episodes():
    # a terminal-view run: 8 training episodes; episodes 1, 2, 4 and 6 were ended by vetoes, so their
    # env episodes did not end: env episodes ended so far 0, 0, 1, 1, 2, 2, 3, 4
    returns = [100, 100, 900, 900, 900, 900, 900, 900]
    base = logs(returns, [0, 5000], [0, 5000], [0, 0], 5000, 4000, 1000)
    terminal = dataclasses.replace(base, env_episodes_ended=np.array([0, 0, 1, 1, 2, 2, 3, 4]))
    rule = Rule(target=800, consecutive=5, window=2, every=5000, budget=5000)
    m = run_metrics(terminal, rule)
    assert m.episodes_to_wins == 7 and m.env_episodes_to_wins == 3  # 5 wins at training episode 7
    assert m.episodes_to_average == 4 and m.env_episodes_to_average == 1  # mean(900, 900) at episode 4
    assert m.env_episodes == 4
    # logs from before the terminal view: every training episode was an env episode
    old = run_metrics(base, rule)
    assert (old.env_episodes_to_wins, old.env_episodes_to_average, old.env_episodes) == (7, 4, 8)


def test_the_agent_alone_target_can_differ_from_the_papers():
    # Hopper: standing scores about 1000 and reaches the paper's 800; the plan's 1700 needs locomotion
    means = [10, 990, 995, 1750, 1800]
    lg = logs(
        [1.0] * 3, [0, 10000, 20000, 30000, 40000], [0, 10000, 20000, 30000, 40000], means, 40000, 40000, 0
    )
    rule = Rule(target=800, consecutive=5, window=2, every=10000, budget=40000, alone_target=1700)
    m = run_metrics(lg, rule)
    assert rule.agent_target == 1700 and Rule(800, 5, 2, 10000, 40000).agent_target == 800
    assert m.env_steps_to_target == 10000 and m.env_steps_to_alone_target == 30000
