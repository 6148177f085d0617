"""The whole pipeline on one env: linearize, auto-tune a coach, derive its bounds, train, report.

``pidlab run ENV`` (and the README's main command on InvertedPendulum-v5) runs, with the
settings of the recipe's ``[pipeline]`` table (:class:`pidlab.rl.recipe.PipelineSettings`):

1. **linearize** the env's model at its model card's operating point;
2. **tune** a coach automatically (:func:`pidlab.controller.autotune.tune`, the chosen preset);
3. **analyze** it: margins per actuator, closed-loop poles, responses, its score alone;
4. **bounds**: estimate and certify its region of attraction in MuJoCo, derive the critical-state
   bounds from it and write them into the spec;
5. **train** the recipe's agent with and without that coach (a :mod:`pidlab.experiment.sweep` sweep);
6. **report**: one page with the margins table, the region picture, the learning curves and the
   agent-alone scores.

Everything lands in one folder::

    OUT/
      pipeline.json        the settings, the command, versions, git SHA, each stage's time
      linearization.json   the linear model (as ``pidlab linearize --json``)
      tuned.toml           the auto-tuned coach; tune.json: what was asked and achieved
      coach.toml           the same coach with its derived [bounds]: the one that trains
      roa.json             the certified region and the bounds
      conditions.toml      the two conditions trained: none and coached
      experiment/          the sweep (runs, checkpoints, its own full report)
      figures/             PNG figures
      report.md, report.html

Run again, the same command skips finished stages and resumes the sweep from its checkpoints. A
folder that holds a pipeline with other settings is refused and left untouched.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

from pidlab.data import source_root
from pidlab.errors import PipelineError
from pidlab.files import atomic_write_text, read_json, write_json
from pidlab.provenance import git_state, package_versions
from pidlab.rl.recipe import (
    PRESETS,
    PipelineSettings,
    default_recipe_path,
    load_pipeline_settings,
    load_recipe,
    recipe_envs,
    recipe_to_dict,
)

PIPELINE_SCHEMA = "pidlab.pipeline/1"
STAGES = ("linearize", "tune", "analyze", "bounds", "train", "report")
CONDITIONS = ("none", "coached")


@dataclass(frozen=True)
class StageRecord:
    """How one stage went: ``done`` (ran now), ``skipped`` (finished before) or ``interrupted``.

    ``seconds`` is its time in this session, ``at`` when it ended.
    """

    name: str
    status: str
    seconds: float
    at: str = ""


@dataclass(frozen=True)
class PipelineResult:
    """Where the pipeline wrote its report, and how each stage went."""

    out: Path
    report_md: Path
    report_html: Path
    stages: tuple[StageRecord, ...]
    interrupted: bool
    failed_runs: int


def settings_for(
    env_id: str,
    *,
    seeds: int | None = None,
    steps: int | None = None,
    preset: str | None = None,
    roa_samples: int | None = None,
    episodes: int | None = None,
) -> PipelineSettings:
    """The env's pipeline settings (its recipe's ``[pipeline]`` table) with overrides applied.

    Raises
    ------
    PipelineError
        An env without a recipe, or an override out of range.
    RecipeError
        A malformed recipe.
    """
    path = default_recipe_path(env_id)
    if not path.is_file():
        raise PipelineError(
            f"ENV {env_id!r}: no recipe {path}; recipes exist for: {', '.join(recipe_envs())}"
        )
    base = load_pipeline_settings(path)
    checks = {"--seeds": (seeds, 1), "--steps": (steps, 1), "--samples": (roa_samples, 1),
              "--episodes": (episodes, 0)}  # fmt: skip
    for flag, (value, low) in checks.items():
        if value is not None and value < low:
            raise PipelineError(f"{flag} {value}: expected an integer >= {low}")
    if preset is not None and preset not in PRESETS:
        raise PipelineError(f"--preset {preset!r}: expected one of {', '.join(PRESETS)}")
    given: dict[str, Any] = {"seeds": seeds, "steps": steps, "preset": preset, "roa_samples": roa_samples,
                             "episodes": episodes}  # fmt: skip
    return replace(base, **{k: v for k, v in given.items() if v is not None})


def _identity(env_id: str, settings: PipelineSettings) -> dict[str, Any]:
    # the coach-alone episodes are recomputed on every run: changing them needs no new folder
    kept = {k: v for k, v in asdict(settings).items() if k != "episodes"}
    return {"schema": PIPELINE_SCHEMA, "env_id": env_id, "settings": kept}


def check_out_folder(out: Path, identity: dict[str, Any]) -> dict[str, Any] | None:
    """The folder's existing record, if it holds this pipeline.

    Raises
    ------
    PipelineError
        The folder holds something else: another pipeline, or files that are not a pipeline's.
    """
    if out.exists() and not out.is_dir():
        raise PipelineError(f"--out {out}: exists and is not a folder")
    record_path = out / "pipeline.json"
    if record_path.exists():
        try:
            record = read_json(record_path)
        except (OSError, json.JSONDecodeError):
            record = None
        if not isinstance(record, dict):
            raise PipelineError(f"--out {out}: pipeline.json is not a pipeline record; use another folder")
        old = record.get("identity", {})
        if old != identity:
            diffs = []
            if old.get("env_id") != identity["env_id"]:
                diffs.append(f"env {old.get('env_id')}")
            for key, value in identity["settings"].items():
                was = old.get("settings", {}).get(key)
                if was != value:
                    diffs.append(f"{key} {was} (now {value})")
            raise PipelineError(
                f"--out {out}: holds a pipeline run with other settings ({', '.join(diffs)}); "
                "run with the same settings to resume, or choose another --out"
            )
        return dict(record)
    if out.exists() and any(out.iterdir()):
        raise PipelineError(f"--out {out}: not empty and holds no pipeline.json; choose another folder")
    return None


@contextmanager
def _stage(
    name: str, records: list[StageRecord], done_before: bool, say: Callable[[str], None]
) -> Iterator[None]:
    index = STAGES.index(name) + 1
    if done_before:
        records.append(StageRecord(name, "skipped", 0.0))
        say(f"[{index}/{len(STAGES)}] {name}: done before, skipped")
        yield
        return
    say(f"[{index}/{len(STAGES)}] {name} ...")
    t0 = time.perf_counter()
    yield
    seconds = time.perf_counter() - t0
    records.append(StageRecord(name, "done", seconds, time.strftime("%Y-%m-%dT%H:%M:%S%z")))
    say(f"[{index}/{len(STAGES)}] {name}: {seconds:.1f} s")


def _write_conditions(out: Path, coach_file: Path) -> Path:
    import tomli_w

    table = {
        "schema": "pidlab.conditions/1",
        "condition": {
            "none": {"description": "No coach: the recipe's agent alone (the baseline).", "coach": "none"},
            "coached": {
                "description": "The coach auto-tuned by this pipeline, with the critical-state bounds "
                "derived from its certified region of attraction, intervening as the recipe's [coaching] "
                "table says; coach steps hidden from the agent.",
                "coach": str(coach_file.resolve()),
            },
        },
    }
    header = "# Written by pidlab run: the two conditions it trains (see pidlab.experiment.conditions).\n"
    return atomic_write_text(out / "conditions.toml", header + tomli_w.dumps(table))


def run_pipeline(
    env_id: str,
    out: str | Path,
    settings: PipelineSettings,
    *,
    workers: int | None = None,
    progress_bar: bool = True,
    argv: Sequence[str] = (),
    say: Callable[[str], None] = print,
) -> PipelineResult:
    """Run (or resume) the whole pipeline on ``env_id`` into ``out``.

    Parameters
    ----------
    env_id : str
        An env with a recipe in ``coach/`` and a model card in ``models/``.
    out : path
        The pipeline's folder (see the module doc).
    settings : PipelineSettings
        From :func:`settings_for`.
    workers : int, optional
        Training runs in parallel (default: the machine's cores).
    progress_bar : bool
        Progress bars on long stages.
    argv : sequence of str
        The command, recorded in ``pipeline.json``.
    say : callable
        Where stage lines go.

    Returns
    -------
    PipelineResult

    Raises
    ------
    PipelineError, RecipeError, SpecError, RegionError, ExperimentError
        One line naming what is wrong; nothing already finished is lost.
    """
    from tqdm.auto import tqdm

    from pidlab.controller.analysis import analyze_coach
    from pidlab.controller.autotune import tune
    from pidlab.controller.pid import Coach
    from pidlab.controller.rollout import coach_alone
    from pidlab.controller.spec import load_spec, save_spec
    from pidlab.experiment.analysis import analyze
    from pidlab.experiment.sweep import plan, run_sweep
    from pidlab.files import save_figure
    from pidlab.linear.linearize import linearize
    from pidlab.linear.lti import analyze_lti
    from pidlab.linear.serialize import linearization_to_dict
    from pidlab.plant.model import load_model
    from pidlab.region.bounds import derive_bounds, with_bounds
    from pidlab.region.roa import estimate_roa
    from pidlab.report.curves import plot_learning_curves
    from pidlab.report.experiment import render_html, write_report
    from pidlab.report.pipeline import PipelineFacts, render_markdown, roa_summary, tune_summary
    from pidlab.report.plots import plot_roa_slice, write_plots
    from pidlab.rl.rundir import spec_digest

    folder = Path(out).resolve()
    identity = _identity(env_id, settings)
    record = check_out_folder(folder, identity)
    recipe = load_recipe(default_recipe_path(env_id))
    try:
        (folder / "figures").mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PipelineError(f"--out {out}: cannot create the folder ({exc.strerror})") from None
    now = time.strftime("%Y-%m-%dT%H:%M:%S%z")
    if record is None:
        record = {"identity": identity, "created": now, "command": list(argv), "resumes": [],
                  "versions": package_versions(), "git": git_state(),
                  "recipe": _shown(recipe.path)}  # fmt: skip
    else:
        record.setdefault("resumes", []).append(
            {"at": now, "command": list(argv), "versions": package_versions(), "git": git_state()}
        )
    write_json(folder / "pipeline.json", record)
    records: list[StageRecord] = []
    loaded = load_model(env_id)
    card = loaded.require_card()
    units = {v.name: v.unit for v in card.observation}

    # 1. linearize (seconds; the JSON is rewritten only when missing)
    lin_path = folder / "linearization.json"
    with _stage("linearize", records, False, say):
        lin = linearize(loaded)
        report_c, report_d = analyze_lti(lin.sys), analyze_lti(lin.sysd)
        if not lin_path.exists():
            write_json(lin_path, linearization_to_dict(lin, report_c, report_d))

    # 2. tune
    tuned_path, tune_json = folder / "tuned.toml", folder / "tune.json"
    with _stage("tune", records, tuned_path.exists() and tune_json.exists(), say):
        if not (tuned_path.exists() and tune_json.exists()):
            with tqdm(desc=f"tuning ({settings.preset})", unit="eval", disable=not progress_bar) as bar:

                def tick(n: int) -> None:
                    bar.update(n - bar.n)

                result = tune(loaded, preset=settings.preset, lin=lin, progress=tick)
            write_json(tune_json, tune_summary(result))
            save_spec(result.spec, tuned_path)
    spec = load_spec(tuned_path)
    tuning = read_json(tune_json)

    # 3. analyze (fast and deterministic: recomputed each time, so the report always matches the code)
    with _stage("analyze", records, False, say):
        coach = Coach(spec, loaded)
        analysis = analyze_coach(coach, loaded)
        if not analysis.stable:
            raise PipelineError(f"{env_id}: the auto-tuned coach's closed loop is unstable; see {tuned_path}")
        written = write_plots(analysis, coach, folder / "figures")
        score = None
        if settings.episodes:
            with tqdm(total=1, desc="coach alone", unit="run", disable=not progress_bar) as bar:
                score = coach_alone(spec, loaded, episodes=settings.episodes)
                bar.update(1)

    # 4. region of attraction and bounds
    coach_path, roa_json = folder / "coach.toml", folder / "roa.json"
    roa_png = folder / "figures" / "roa.png"
    lp0 = spec.loops[0]
    pair = (lp0.signal, lp0.rate_signal or lp0.signal)
    tuned_digest = spec_digest(spec)
    done = (
        coach_path.exists()
        and roa_png.exists()
        and roa_json.exists()
        and read_json(roa_json).get("tuned_sha256") == tuned_digest
    )
    with _stage("bounds", records, done, say):
        if not done:
            with tqdm(total=100, desc="region", unit="%", disable=not progress_bar) as bar:
                shown = {"phase": ""}

                def roa_progress(stage: str, fraction: float | None) -> None:
                    # each phase (CasADi level, bisection, final check) runs from 0 to 100 %
                    phase = stage.split(" (")[0]
                    if phase != shown["phase"]:
                        shown["phase"] = phase
                        bar.set_description_str(f"region: {phase}")
                    bar.n = int(100 * (fraction or 0.0))
                    bar.refresh()

                region, kept = estimate_roa(
                    spec, loaded, samples=settings.roa_samples, seed=0, keep_trajectories=80,
                    record=pair if pair[0] != pair[1] else None, progress=roa_progress,
                )  # fmt: skip
                bar.set_description_str("region: deriving the critical bounds")
                bar.n = 0
                bar.refresh()
                crit = derive_bounds(region, spec, loaded, seed=0)
                bar.n = 100
                bar.refresh()
            fig = plot_roa_slice(region, pair, kept, units, bounds=crit)
            save_figure(fig, roa_png)
            write_json(roa_json, {**roa_summary(region, crit, pair), "tuned_sha256": tuned_digest})
            save_spec(with_bounds(spec, crit), coach_path)
    coached = load_spec(coach_path)
    roa_facts = read_json(roa_json)

    # 5. train with and without the coach
    conditions = _write_conditions(folder, coach_path)
    sweep_plan = plan(
        [env_id], list(CONDITIONS), list(range(settings.seeds)), folder / "experiment",
        conditions_file=conditions, steps=settings.steps,
    )  # fmt: skip
    with _stage("train", records, False, say):
        sweep = run_sweep(sweep_plan, workers=workers, argv=argv, progress_bar=progress_bar)
    if sweep.interrupted:
        records[-1] = replace(records[-1], status="interrupted")
        _finish_record(folder, record, records)
        return PipelineResult(folder, folder / "report.md", folder / "report.html", tuple(records), True,
                              sweep.count("failed"))  # fmt: skip

    # 6. report
    with _stage("report", records, False, say):
        exp_record = read_json(sweep_plan.out / "experiment.json")
        results = analyze(exp_record["identity"], sweep_plan.out, sweep_plan.recipes)
        write_report(sweep_plan, progress_bar=False, analysis=results)
        curves = folder / "figures" / "learning-curves.png"
        if (env_id, "none") in results.cells or (env_id, "coached") in results.cells:
            save_figure(plot_learning_curves(results, env_id), curves)
        _finish_record(folder, record, records)
        facts = PipelineFacts(
            env_id=env_id,
            settings=settings,
            record=read_json(folder / "pipeline.json"),
            coaching=recipe_to_dict(recipe)["coaching"],
            lti=report_c,
            control_dt=float(lin.control_dt),
            tuning=tuning,
            spec=coached,
            analysis=analysis,
            score=score,
            roa=roa_facts,
            units=units,
            results=results,
            figures=tuple(p.relative_to(folder).as_posix() for p in written),
            roa_figure=roa_png.relative_to(folder).as_posix(),
            curves_figure=curves.relative_to(folder).as_posix() if curves.exists() else None,
        )
        text = render_markdown(facts)
        md = atomic_write_text(folder / "report.md", text)
        page = atomic_write_text(folder / "report.html", render_html(text, f"pidlab run {env_id}"))
    _finish_record(folder, record, records)
    return PipelineResult(folder, md, page, tuple(records), False, sweep.count("failed"))


def _shown(path: str | None) -> str:
    """A path as the report shows it: relative to pidlab's source tree when inside it."""
    root = source_root()
    p = Path(path or "").resolve()
    return p.relative_to(root).as_posix() if root is not None and p.is_relative_to(root) else str(p)


def _finish_record(folder: Path, record: dict[str, Any], records: list[StageRecord]) -> None:
    """Write the stage times into ``pipeline.json``.

    Each stage keeps the time of its last run; training is summed over the sessions that trained
    (a resumed sweep only trains what was left).
    """
    stages = dict(record.get("stages", {}))
    pending = dict(record.get("pending_train_s", {}))
    for r in records:
        if r.name == "train" and r.status in ("done", "interrupted"):
            total = float(pending.get("seconds", 0.0)) + r.seconds
            if r.status == "interrupted":
                pending = {"seconds": round(total, 2)}
                continue
            pending = {}
            stages[r.name] = {"seconds": round(total, 2), "at": r.at}
        elif r.status == "done":
            stages[r.name] = {"seconds": round(r.seconds, 2), "at": r.at}
    record["stages"] = stages
    if pending:
        record["pending_train_s"] = pending
    else:
        record.pop("pending_train_s", None)
    write_json(folder / "pipeline.json", record)
