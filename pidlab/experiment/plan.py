"""The pre-registered analysis plan (docs/analysis-plan.md) as the reports apply it.

The plan was committed before the confirmatory runs it governs (:data:`PLAN_COMMIT`); every
report cites that commit and says whether its sweep is confirmatory (the plan's fresh seeds,
:data:`CONFIRMATORY_SEEDS`) or a pilot. The numbers here are the plan's; ``tests/test_plan.py``
checks that the document says the same.
"""

from __future__ import annotations

from collections.abc import Sequence

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


def confirmatory_seeds(conditions: Sequence[str] = ()) -> tuple[int, ...]:
    """The fresh seeds that confirm a sweep of ``conditions`` (an amendment's own, else the plan's)."""
    own = {AMENDMENT_SEEDS[k] for k in amendments_of(conditions) if k in AMENDMENT_SEEDS}
    return own.pop() if len(own) == 1 else CONFIRMATORY_SEEDS


def ungoverned(conditions: Sequence[str]) -> tuple[str, ...]:
    """The conditions that neither the plan nor an amendment governs (their comparisons were not planned)."""
    return tuple(c for c in conditions if c not in CONFIRMATORY_CONDITIONS and c not in AMENDMENTS)


PLAN_ALGORITHMS = ("ppo",)
"""The agents the plan and its amendments govern (section 2: PPO with each env's recipe)."""


def unplanned_algorithms(algorithms: Sequence[str]) -> tuple[str, ...]:
    """The algorithms of a sweep that the plan does not govern."""
    return tuple(a for a in algorithms if a not in PLAN_ALGORITHMS)


def role(seeds: Sequence[int], conditions: Sequence[str] = (), algorithms: Sequence[str] = ("ppo",)) -> str:
    """The sweep's standing under the plan.

    On exactly its fresh seeds (:func:`confirmatory_seeds`): ``confirmatory``, or ``exploratory``
    when it holds a condition the plan does not govern (:func:`ungoverned`) or trains another agent
    than the plan's (:data:`PLAN_ALGORITHMS`). On other seeds: ``pilot``.
    """
    if tuple(sorted(seeds)) != confirmatory_seeds(conditions):
        return "pilot"
    planned = not ungoverned(conditions) and not unplanned_algorithms(algorithms)
    return "confirmatory" if planned else "exploratory"


AMENDMENTS: dict[str, int] = {
    "warm-start": 1,
    "warm-start-shield": 1,
    "blend": 2,
    "rollin": 2,
    "rescue-veto": 2,
    "warm-start-veto": 2,
    "warm-start-keep": 3,
    "warm-start-keep-shield": 3,
    "warm-start-keep-shield-short": 4,
    "residual": 5,
}
"""Condition -> the amendment of the plan that governs it (added before its runs)."""

AMENDMENT_SEEDS: dict[int, tuple[int, ...]] = {4: tuple(range(110, 120))}
"""Amendment -> its own fresh confirmatory seeds (the others confirm on :data:`CONFIRMATORY_SEEDS`)."""


def amendments_of(conditions: Sequence[str]) -> tuple[int, ...]:
    """The amendments that govern ``conditions`` (in order; none for the plan's own conditions)."""
    return tuple(sorted({AMENDMENTS[c] for c in conditions if c in AMENDMENTS}))


def citation(
    seeds: Sequence[int], conditions: Sequence[str] = (), algorithms: Sequence[str] = ("ppo",)
) -> str:
    """The sentence a report opens its analysis with (naming the amendments that govern ``conditions``)."""
    text = (
        f"Analysed under the pre-registered analysis plan ({PLAN_FILE}, committed in {PLAN_COMMIT[:7]} "
        "before the confirmatory runs)."
    )
    amended = amendments_of(conditions)
    if amended:
        names = " and ".join(f"Amendment {k}" for k in amended)
        text += f" Its couplings are governed by the plan's {names}, each added before the runs it governs."
    fresh = confirmatory_seeds(conditions)
    span = f"{fresh[0]}-{fresh[-1]}"
    kind = role(seeds, conditions, algorithms)
    if kind == "confirmatory":
        return text + f" **Confirmatory sweep**: the plan's fresh seeds {span}; its verdicts are the plan's."
    if kind == "exploratory":
        other = unplanned_algorithms(algorithms)
        what = (f"the agent {', '.join(a.upper() for a in other)} (it governs PPO)" if other
                else ", ".join(ungoverned(conditions)))  # fmt: skip
        return text + (
            f" **Exploratory sweep**: neither the plan nor an amendment governs {what}, so its tests "
            f"were not planned; on the plan's seeds {span} too, its verdicts describe these runs and "
            "confirm nothing."
        )
    return text + (
        f" **Pilot (exploratory) sweep**: these seeds are not the plan's confirmatory seeds {span}, so its "
        "verdicts describe these runs and confirm nothing."
    )
