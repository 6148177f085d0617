"""The pre-registered analysis plan (docs/analysis-plan.md) as the reports apply it.

The plan was committed before the confirmatory runs it governs (:data:`PLAN_COMMIT`); every
report cites that commit and says whether its sweep is confirmatory (the plan's fresh seeds,
:data:`CONFIRMATORY_SEEDS`) or a pilot. The numbers here are the plan's; ``tests/test_plan.py``
checks that the document says the same.
"""

from __future__ import annotations

import statistics
from collections.abc import Sequence
from dataclasses import dataclass

PLAN_FILE = "docs/analysis-plan.md"
PLAN_COMMIT = "f00fabfb1e3c5a3c571ad8f09bca77b761ebdc91"
CONFIRMATORY_SEEDS = tuple(range(100, 110))

CONFIRMATORY_CONDITIONS = ("none", "paper", "rescue-terminal")

BUDGETS: dict[str, int] = {
    "InvertedPendulum-v5": 50_000,
    "InvertedDoublePendulum-v5": 200_000,
    "Hopper-v5": 300_000,
    "Walker2d-v5": 1_000_000,
}
"""Env id -> the confirmatory budget, env steps (coach steps included)."""

EVALUATION_EVERY: dict[str, int] = {
    "InvertedPendulum-v5": 2_500,
    "InvertedDoublePendulum-v5": 10_000,
    "Hopper-v5": 10_000,
    "Walker2d-v5": 10_000,
}
"""Env id -> env steps between agent-alone evaluations (the shipped recipes' ``evaluation.every``)."""

ALONE_TARGETS: dict[str, float] = {"Hopper-v5": 1700.0, "Walker2d-v5": 2200.0}
"""Env id -> the agent-alone (locomotion) target, where the paper's target is reached by standing."""

PRIMARY = ("falls", "env_steps_to_alone_target", "final_score")
"""The primary measures: one Holm family per env (with every coached condition's tests)."""

SECONDARY = ("env_episodes_to_wins", "env_episodes_to_average")
"""The paper's measures in env episodes (a second family; plus the paper's target in env steps
where the agent-alone target differs from it)."""

PAPER_TARGET_STEPS = "env_steps_to_target"


def alone_target(env_id: str, win_target: float) -> float | None:
    """The plan's agent-alone target of ``env_id`` when it differs from ``win_target`` (else None)."""
    target = ALONE_TARGETS.get(env_id)
    return None if target is None or target == win_target else target


def secondary_measures(env_id: str, win_target: float) -> tuple[str, ...]:
    """The secondary family's measures of ``env_id``."""
    extra = (PAPER_TARGET_STEPS,) if alone_target(env_id, win_target) is not None else ()
    return SECONDARY + extra


PAPER_ENVS = tuple(BUDGETS)
"""The paper's four envs, which the plan governs."""


@dataclass(frozen=True)
class Amendment:
    """An amendment of the plan: the conditions it governs, where, on which seeds, with which agent.

    Attributes
    ----------
    number : int
        Its number in docs/analysis-plan.md ("### Amendment N").
    conditions : tuple of str
        The conditions (coach/conditions.toml) it governs.
    envs : tuple of str
        The envs it governs them on.
    seeds : tuple of int
        Its fresh confirmatory seeds.
    algorithms : tuple of str
        The agents it governs (besides the plan's PPO).
    """

    number: int
    conditions: tuple[str, ...]
    envs: tuple[str, ...] = PAPER_ENVS
    seeds: tuple[int, ...] = CONFIRMATORY_SEEDS
    algorithms: tuple[str, ...] = ("ppo",)


AMENDMENT_LIST: tuple[Amendment, ...] = (
    Amendment(1, ("warm-start", "warm-start-shield")),
    Amendment(2, ("blend", "rollin", "rescue-veto", "warm-start-veto")),
    Amendment(3, ("warm-start-keep", "warm-start-keep-shield")),
    Amendment(4, ("warm-start-keep-shield-short",), seeds=tuple(range(110, 120))),
    Amendment(5, ("residual",)),
    Amendment(7, ("warm-start-keep-shield-short",), envs=("Hopper-v5", "Walker2d-v5")),
    Amendment(
        8, ("none-sac",), envs=("InvertedPendulum-v5", "InvertedDoublePendulum-v5"), algorithms=("sac",)
    ),
    Amendment(9, ("rescue-terminal-full",), envs=("InvertedDoublePendulum-v5",)),
    Amendment(10, ("warm-start-hold",), envs=("InvertedDoublePendulum-v5",), seeds=tuple(range(110, 120))),
    Amendment(11, ("rescue-terminal-full",), envs=("InvertedPendulum-v5",)),
    Amendment(12, ("rescue-terminal-edge",), envs=("InvertedPendulum-v5",)),
    Amendment(
        13,
        ("rescue-replay", "rescue-value", "rescue-propose", "warm-start-keep-shield-short"),
        envs=("InvertedPendulum-v5",),
        algorithms=("sac",),
    ),
    Amendment(14, ("rescue-terminal-edge-model",), envs=("InvertedPendulum-v5",)),
    Amendment(15, ("rescue-terminal-full-learned",), envs=("InvertedDoublePendulum-v5",)),
    Amendment(16, ("rescue-terminal-room-full",), envs=("Hopper-v5",)),
    Amendment(17, ("rescue-terminal-full-scoped",), envs=("InvertedDoublePendulum-v5",)),
    Amendment(18, ("none-sac",), envs=("Hopper-v5",), algorithms=("sac",)),
    Amendment(
        19, ("warm-start-hold-short",), envs=("InvertedDoublePendulum-v5",), seeds=tuple(range(120, 130))
    ),
    Amendment(20, ("rescue-terminal-room-focus",), envs=("Hopper-v5",)),
    Amendment(21, ("rescue-terminal-room-focus-learned",), envs=("Hopper-v5",)),
    Amendment(22, ("none-sac",), envs=("Walker2d-v5",), algorithms=("sac",)),
    Amendment(
        23, ("rescue-replay", "demo-replay-short"), envs=("InvertedDoublePendulum-v5",), algorithms=("sac",)
    ),
    Amendment(24, ("rescue-replay-room",), envs=("Hopper-v5",), algorithms=("sac",)),
    Amendment(25, ("demo-replay-balance",), envs=("Walker2d-v5",), algorithms=("sac",)),
)
"""Every amendment that governs conditions, in the plan's order (Amendment 6 is a procedure)."""

PLAN_ALGORITHMS = ("ppo",)
"""The agent the plan governs (section 2: PPO with each env's recipe); amendments may add others."""


def governing(condition: str, env: str) -> tuple[Amendment, ...]:
    """The amendments that govern ``condition`` on ``env`` (none for the plan's own conditions)."""
    return tuple(a for a in AMENDMENT_LIST if condition in a.conditions and env in a.envs)


def _amendments(conditions: Sequence[str], envs: Sequence[str]) -> tuple[Amendment, ...]:
    return tuple(a for a in AMENDMENT_LIST if any(a in governing(c, e) for c in conditions for e in envs))


def fresh_seed_sets(
    conditions: Sequence[str] = (), envs: Sequence[str] = PAPER_ENVS
) -> tuple[tuple[int, ...], ...]:
    """The seed sets that may confirm a sweep of ``conditions`` on ``envs`` (the plan's, its amendments')."""
    sets = [CONFIRMATORY_SEEDS, *(a.seeds for a in _amendments(conditions, envs))]
    return tuple(dict.fromkeys(sets))


def _on_seeds(seeds: Sequence[int], conditions: Sequence[str], envs: Sequence[str]) -> tuple[Amendment, ...]:
    fresh = tuple(sorted(seeds))
    return tuple(a for a in _amendments(conditions, envs) if a.seeds == fresh)


def amendments_of(
    conditions: Sequence[str], envs: Sequence[str] = PAPER_ENVS, seeds: Sequence[int] | None = None
) -> tuple[int, ...]:
    """The numbers of the amendments that govern ``conditions`` on ``envs`` (on ``seeds`` when given)."""
    found = _amendments(conditions, envs) if seeds is None else _on_seeds(seeds, conditions, envs)
    return tuple(sorted({a.number for a in found}))


def ungoverned(
    conditions: Sequence[str], envs: Sequence[str] = PAPER_ENVS, seeds: Sequence[int] = CONFIRMATORY_SEEDS
) -> tuple[str, ...]:
    """The conditions that neither the plan nor an amendment governs on all ``envs`` with ``seeds``."""
    fresh = tuple(sorted(seeds))

    def planned(c: str, e: str) -> bool:
        if c in CONFIRMATORY_CONDITIONS:
            return True
        return any(a.seeds == fresh for a in governing(c, e))

    return tuple(c for c in conditions if not all(planned(c, e) for e in envs))


def unplanned_algorithms(
    algorithms: Sequence[str],
    conditions: Sequence[str] = (),
    envs: Sequence[str] = PAPER_ENVS,
    seeds: Sequence[int] = CONFIRMATORY_SEEDS,
) -> tuple[str, ...]:
    """The algorithms of a sweep that neither the plan nor an amendment of its conditions governs."""
    allowed = set(PLAN_ALGORITHMS).union(*(a.algorithms for a in _on_seeds(seeds, conditions, envs)))
    return tuple(a for a in algorithms if a not in allowed)


def role(
    seeds: Sequence[int],
    conditions: Sequence[str] = (),
    algorithms: Sequence[str] = ("ppo",),
    envs: Sequence[str] = PAPER_ENVS,
) -> str:
    """The sweep's standing under the plan.

    On exactly a set of fresh seeds (:func:`fresh_seed_sets`): ``confirmatory`` when the plan or
    its amendments govern every condition on every env on those seeds, with the agents they name;
    else ``exploratory`` (a condition not governed there, :func:`ungoverned`, or an agent not
    governed, :func:`unplanned_algorithms`). On other seeds: ``pilot``.
    """
    if tuple(sorted(seeds)) not in fresh_seed_sets(conditions, envs):
        return "pilot"
    planned = not ungoverned(conditions, envs, seeds) and not unplanned_algorithms(
        algorithms, conditions, envs, seeds
    )
    return "confirmatory" if planned else "exploratory"


def _span(seeds: Sequence[int]) -> str:
    return f"{seeds[0]}-{seeds[-1]}"


def citation(
    seeds: Sequence[int],
    conditions: Sequence[str] = (),
    algorithms: Sequence[str] = ("ppo",),
    envs: Sequence[str] = PAPER_ENVS,
) -> str:
    """The sentence a report opens its analysis with (naming the amendments that govern ``conditions``)."""
    text = (
        f"Analysed under the pre-registered analysis plan ({PLAN_FILE}, committed in {PLAN_COMMIT[:7]} "
        "before the confirmatory runs)."
    )
    kind = role(seeds, conditions, algorithms, envs)
    amended = amendments_of(conditions, envs, None if kind == "pilot" else seeds)
    if amended:
        names = " and ".join(f"Amendment {k}" for k in amended)
        text += f" Its couplings are governed by the plan's {names}, each added before the runs it governs."
    if kind == "confirmatory":
        span = _span(sorted(seeds))
        return text + f" **Confirmatory sweep**: the plan's fresh seeds {span}; its verdicts are the plan's."
    if kind == "exploratory":
        other = unplanned_algorithms(algorithms, conditions, envs, seeds)
        names = ", ".join(ungoverned(conditions, envs, seeds))
        what = f"the agent {', '.join(a.upper() for a in other)} in this sweep" if other else names
        return text + (
            f" **Exploratory sweep**: neither the plan nor an amendment governs {what} on these envs and "
            f"seeds ({_span(sorted(seeds))}), so its tests were not planned; its verdicts describe these "
            "runs and confirm nothing."
        )
    fresh = " or ".join(_span(s) for s in fresh_seed_sets(conditions, envs))
    return text + (
        f" **Pilot (exploratory) sweep**: these seeds are not the plan's confirmatory seeds {fresh}, so its "
        "verdicts describe these runs and confirm nothing."
    )


@dataclass(frozen=True)
class PlainLearner:
    """A plain learner's runs, as Amendment 8's rule reads them.

    Attributes
    ----------
    condition : str
        ``none`` (PPO) or ``none-sac``.
    steps_to_target : tuple of float
        Per run, env steps to the agent-alone target, reached and kept (``inf``: never reached).
    final_scores : tuple of float
        Per run, the final agent-alone score.
    """

    condition: str
    steps_to_target: tuple[float, ...]
    final_scores: tuple[float, ...]


def best_plain_baseline(learners: Sequence[PlainLearner]) -> PlainLearner:
    """The best plain baseline by Amendment 8's rule (docs/analysis-plan.md).

    The learner with the smaller median env steps to the agent-alone target (a run that never
    reached it counts as +inf); on a tie, the larger median final agent-alone score; then ``none``.
    The rule picks one whether or not a test separates them.

    Raises
    ------
    ValueError
        No learner, or a learner without runs.
    """
    if not learners or any(not x.steps_to_target or not x.final_scores for x in learners):
        raise ValueError("best_plain_baseline: expected at least one learner, each with runs")

    def key(x: PlainLearner) -> tuple[float, float, int]:
        median = statistics.median
        return (median(x.steps_to_target), -median(x.final_scores), 0 if x.condition == "none" else 1)

    return min(learners, key=key)
