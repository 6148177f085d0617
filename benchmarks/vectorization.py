"""Does learning per env step survive vectorized training? 1 env against the recipes' vectorized settings.

Reads the uncoached runs that ``benchmarks/vectorization.sh`` trained (published, per-run logs only,
in docs/results/vectorization/ENV.VARIANT/runs/), and writes docs/vectorization.md and its figures.
Every number comes from those files, so a reader can rerun this without training:

    .venv/bin/python benchmarks/vectorization.py            # write docs/vectorization.md
    .venv/bin/python benchmarks/vectorization.py --check    # exit 1 if the page differs from its runs

Measures (pidlab's, :mod:`pidlab.experiment.metrics`): env steps until the agent alone reaches the
recipe's target and keeps it to the end of the run (sustained hit, +inf when never), the final
agent-alone score, and the mean agent-alone score over the run's evaluations (the area under the
learning curve, divided by its length: it credits learning early even when no run reaches the
target). IQM with 95 % stratified-bootstrap intervals, P(vectorized better than 1 env) with its
interval, and the exact two-sided rank-sum p-value.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from bench_cli import Parser, run

from pidlab.experiment.analysis import RunData, load_run, rule_of
from pidlab.experiment.comparison import Comparison, Measure, raw_comparison
from pidlab.experiment.stats import Estimate, bootstrap_ci
from pidlab.files import atomic_write_text
from pidlab.report.experiment import estimate_text, p_text
from pidlab.rl.rundir import load_run_config

ROOT = Path(__file__).resolve().parents[1]
PUBLISHED = ROOT / "docs" / "results" / "vectorization"
PAGE = ROOT / "docs" / "vectorization.md"
IMAGES = ROOT / "docs" / "images"
# (env, baseline variant, vectorized variant, why it was run), in the order the comparisons were made
DESIGN = (
    ("InvertedPendulum-v5", "n1", "n8",
     "first candidate: 8 envs, a rollout of 64 so that the zoo's batch_size 64 fits (half the updates)"),
    ("InvertedPendulum-v5", "n1", "n4",
     "second candidate, run after the first was worse: 4 envs, the zoo's rollout of 32 and the same updates"),
    ("Hopper-v5", "n1-b32", "n8-b32", "8 envs, the zoo's rollout of 512 and the same updates"),
)  # fmt: skip
MEASURES = (
    Measure("env_steps_to_target", True, "env steps to target, sustained"),
    Measure("final_score", False, "final agent-alone score"),
    Measure("mean_score", False, "mean agent-alone score over the run"),
)


@dataclass(frozen=True)
class Variant:
    """The runs of one recipe variant."""

    name: str
    n_envs: int
    n_steps: int
    batch_size: int
    runs: tuple[RunData, ...]


def recipe_budget(env_id: str) -> int:
    """The shipped recipe's budget, env steps."""
    from pidlab.rl.recipe import load_recipe

    return load_recipe(ROOT / "coach" / f"{env_id}.toml").steps


def load_variant(env_id: str, name: str) -> Variant:
    """Every finished run of ``ENV.name`` in the published folder."""
    root = PUBLISHED / f"{env_id}.{name}" / "runs" / env_id / "none"
    runs, recipe = [], None
    for folder in sorted(root.glob("seed-*"), key=lambda p: int(p.name[5:])):
        recipe, _, _ = load_run_config(folder)
        run = load_run(folder, env_id, "none", int(folder.name[5:]), rule_of(recipe))
        if run is not None and run.completed:
            runs.append(run)
    if recipe is None:
        raise SystemExit(
            f"vectorization: {root}: no runs (run benchmarks/vectorization.sh, then publish them)"
        )
    hp = recipe.hyperparameters
    return Variant(name, recipe.n_envs, int(hp["n_steps"]), int(hp["batch_size"]), tuple(runs))


def values(v: Variant, name: str) -> np.ndarray:
    """The measure per run (+inf: never reached)."""
    if name == "mean_score":
        return np.array([float(np.mean(r.eval_means)) for r in v.runs])
    raw = [getattr(r.metrics, name) for r in v.runs]
    return np.array([np.inf if x is None else float(x) for x in raw])


def _iqm(x: np.ndarray) -> Estimate:
    return bootstrap_ci([x.tolist()], reps=2000, seed=0)


def comparisons(base: Variant, vec: Variant) -> list[tuple[Measure, Comparison]]:
    """``vec`` against ``base`` on every measure (P(vec better) with its interval, the exact test)."""
    return [(m, raw_comparison(values(vec, m.name), values(base, m.name), m, reps=2000)) for m in MEASURES]


def worse_on(base: Variant, vec: Variant) -> list[str]:
    """The measures on which ``vec`` is clearly worse: P(vec better) has its whole interval below 0.5."""
    return [m.label for m, c in comparisons(base, vec) if c.improvement.high < 0.5]


def decision(base: Variant, vec: Variant) -> str:
    """The rule the recipes follow, applied, and what the intervals allow."""
    worse = worse_on(base, vec)
    if worse:
        return f"**Not adopted**: `{vec.name}` learns less per env step ({'; '.join(worse)})."
    m, c = max(comparisons(base, vec), key=lambda mc: mc[1].improvement.high - mc[1].improvement.low)
    low, high = c.improvement.low, c.improvement.high
    # P = 0.25 or 0.75 (one variant's run beats the other's three times in four) is a large effect
    allows = (
        "anything from a large loss to a large gain"
        if low <= 0.25 and high >= 0.75
        else f"anything from a loss of P = {low:.2f} to a gain of P = {high:.2f}"
    )
    return (
        f"**Adopted**: `{vec.name}` is not worse per env step on any measure (every interval of "
        f"P(better) reaches 0.5), but that does not rule out losses: with {len(base.runs)} seeds per "
        f"variant the widest interval, [{low:.2f}, {high:.2f}] ({m.label}), allows {allows} "
        "(P = 0.25 or 0.75: a run of one variant beats a run of the other three times in four). "
        f"`{vec.name}` was adopted because no measure showed a loss and it trains more env steps per "
        "wall-clock second ([training throughput](training-throughput.md)), not because losses were "
        "ruled out."
    )


def table(env_id: str, base: Variant, vec: Variant) -> list[str]:
    """The comparison table of one env (markdown lines)."""
    lines = [
        f"| measure | {base.name}: {base.n_envs} env | {vec.name}: {vec.n_envs} envs | "
        f"P({vec.name} better) [95 % CI] | exact p |",
        "|---|---|---|---|---|",
    ]
    for m in MEASURES:
        a, b = values(vec, m.name), values(base, m.name)
        c = raw_comparison(a, b, m, reps=2000)
        reached = ""
        if m.name == "env_steps_to_target":
            reached = (
                f" (reached: {int(np.isfinite(b).sum())}/{b.size} and {int(np.isfinite(a).sum())}/{a.size})"
            )
        lines.append(
            f"| {m.label}{reached} | {estimate_text(_iqm(b), m.name)} | {estimate_text(_iqm(a), m.name)} | "
            f"{c.improvement.value:.2f} [{c.improvement.low:.2f}, {c.improvement.high:.2f}] | "
            f"{p_text(c.test.p_value)} |"
        )
    return lines


def _minibatches(v: Variant) -> str:
    k = max(v.n_envs * v.n_steps // v.batch_size, 1)
    return f"{k} minibatch" + ("es" if k > 1 else "")


def _setting(v: Variant) -> str:
    env = "env" if v.n_envs == 1 else "envs"
    return (
        f"{v.n_envs} {env}, n_steps {v.n_steps} per env, batch_size {v.batch_size} "
        f"(rollout {v.n_envs * v.n_steps}; {_minibatches(v)} per epoch)"
    )


def plot_curves(env_id: str, variants: tuple[Variant, ...], ax: plt.Axes | None = None) -> plt.Axes:
    """Agent-alone score against env steps: every run thin, the mean over runs thick."""
    ax = ax if ax is not None else plt.subplots(figsize=(6.4, 3.6))[1]
    for v, color in zip(variants, ("tab:blue", "tab:orange"), strict=True):
        for r in v.runs:
            ax.plot(r.eval_grid, r.eval_means, color=color, lw=0.6, alpha=0.35)
        grid = v.runs[0].eval_grid
        mean = np.mean([r.eval_means[: grid.size] for r in v.runs], axis=0)
        ax.plot(
            grid, mean, color=color, lw=2.2, label=f"{v.name}: {v.n_envs} env{'s' if v.n_envs > 1 else ''}"
        )
    ax.set_xlabel("env steps")
    ax.set_ylabel("agent-alone return")
    ax.set_title(env_id)
    ax.legend(loc="lower right")
    return ax


def page(figures: dict[tuple[str, str], str]) -> str:
    """docs/vectorization.md."""
    out = [
        "# Vectorized training: learning per env step",
        "",
        "<!-- written by benchmarks/vectorization.py from docs/results/vectorization: do not edit -->",
        "",
        "Before the recipes train on several envs at once (faster: one batched forward pass of the policy",
        "per step of all envs), we checked whether an agent learns less per env step. Uncoached PPO,",
        "the recipe's hyperparameters, the same seeds; the vectorized variant changes only `n_envs`,",
        "`n_steps` (per env) and `batch_size`, as each table's header says.",
        "Runs: `bash benchmarks/vectorization.sh`;",
        "this page: `.venv/bin/python benchmarks/vectorization.py`.",
        "Each run's logs are in `docs/results/vectorization/`.",
        "",
        "IQM over seeds with 95 % stratified-bootstrap intervals; P(better) is the probability that a run",
        "of the vectorized variant beats a run with one env (0.5: no difference), with the exact",
        'two-sided rank-sum p-value. "Env steps to target" is the first evaluation from which the agent',
        "alone keeps the recipe's target (800) to the end of the run; a run that never does counts as",
        "+inf (\u221e), so the IQM is \u221e when more than a quarter of the runs missed.",
        "",
        "The rule: a vectorized variant is adopted only if it is not clearly worse per env step on any",
        "measure (every 95 % interval of P(vectorized better) reaches 0.5). With few seeds that shows only",
        "that no loss was detected, not that none exists: each decision below says which losses its",
        "intervals still allow. Speed is measured separately, on an otherwise idle machine:",
        "[training throughput](training-throughput.md).",
        "",
    ]
    for env_id, b, v, why in DESIGN:
        base, vec = load_variant(env_id, b), load_variant(env_id, v)
        budget = base.runs[0].budget
        out += [
            f"## {env_id}: `{vec.name}` against `{base.name}`",
            "",
            f"{len(base.runs)} seeds each, {budget:,} env steps per run "
            f"({budget / recipe_budget(env_id):.0%} of the recipe's budget of {recipe_budget(env_id):,}).",
            "",
            f"Why: {why}.",
            "",
            f"- `{base.name}`: {_setting(base)}",
            f"- `{vec.name}`: {_setting(vec)}",
            "",
            *table(env_id, base, vec),
            "",
            decision(base, vec),
            "",
            f"![{env_id}: {vec.name} against {base.name}](images/{figures[(env_id, v)]})",
            "",
        ]
    return "\n".join(out)


def main() -> int:
    parser = Parser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="exit 1 if docs/vectorization.md differs")
    args = parser.parse_args()
    figures = {(env_id, v): f"vectorization-{env_id}-{v}.png" for env_id, _, v, _ in DESIGN}
    text = page(figures)
    if args.check:
        same = PAGE.is_file() and PAGE.read_text() == text
        print(f"{PAGE}: {'matches its runs' if same else 'differs from its runs'}")
        return 0 if same else 1
    for env_id, b, v, _ in DESIGN:
        fig, ax = plt.subplots(figsize=(6.4, 3.6))
        plot_curves(env_id, (load_variant(env_id, b), load_variant(env_id, v)), ax)
        fig.tight_layout()
        fig.savefig(IMAGES / figures[(env_id, v)], dpi=110)
        plt.close(fig)
    atomic_write_text(PAGE, text)
    print(text)
    return 0


if __name__ == "__main__":
    run(main)
