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
                           (a pidlab.provenance.Record)
      linearization.json   the linear model (as ``pidlab linearize --json``)
      tuned.toml           the auto-tuned coach; tune.json: what was asked and achieved
      coach.toml           the same coach with its derived [bounds]: the one that trains
      roa.json             the certified region and the bounds
      conditions.toml      the two conditions trained: none and coached
      experiment/          the sweep (runs, checkpoints, its own full report)
      figures/             PNG figures
      report.md, report.html

Run again, the same command skips finished stages, reads back the rescue simulations a stopped
bounds stage had done (kept in ``.rescue-labels/`` until the stage ends), and resumes the sweep
from its checkpoints. A
folder that holds a pipeline with other settings is refused and left untouched. Everything the
pipeline reads back (its record, the files of finished stages, the experiment's record) is checked
before it writes anything, and a damaged one is named in one line. The pipeline holds the lock of
OUT (:func:`pidlab.provenance.hold_lock`) from start to end: a second command in it is refused.
"""

from __future__ import annotations

import shlex
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import AbstractContextManager, contextmanager
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pidlab.checks import MAX_SAMPLES, MAX_SEEDS, integer, path_argument
from pidlab.controller.rollout import MAX_EPISODES
from pidlab.data import source_root
from pidlab.errors import PidlabError, PipelineError
from pidlab.files import atomic_write_text, load_json, read_json, write_json
from pidlab.provenance import (
    Record,
    Refusals,
    add_resume,
    check_folder,
    hold_lock,
    new_record,
    now,
    read_record,
    write_record,
)
from pidlab.rl.recipe import (
    MAX_STEPS,
    PRESETS,
    PipelineSettings,
    Recipe,
    default_recipe_path,
    load_pipeline_settings,
    load_recipe,
    recipe_envs,
    recipe_to_dict,
)

if TYPE_CHECKING:
    from pidlab.controller.analysis import CoachAnalysis
    from pidlab.controller.rollout import CoachScore
    from pidlab.controller.spec import CoachSpec
    from pidlab.experiment.sweep import Plan, SweepResult
    from pidlab.linear.linearize import Linearization
    from pidlab.linear.lti import LtiReport
    from pidlab.plant.model import LoadedModel
    from pidlab.region.bounds import CriticalBounds
    from pidlab.region.roa import RegionOfAttraction
    from pidlab.report.pipeline import Evidence

PIPELINE_SCHEMA = "pidlab.pipeline/1"
STAGES = ("linearize", "tune", "analyze", "bounds", "train", "report")
CONDITIONS = ("none", "coached")
RESCUE_JOURNAL = ".rescue-labels"
"""The bounds stage keeps each rescue simulation's outcome here until the stage ends, so that a
stopped pipeline resumes its rescue region instead of simulating it again
(:mod:`pidlab.region.journal`)."""


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
    condition: str | None = None,
) -> PipelineSettings:
    """The env's pipeline settings (its recipe's ``[pipeline]`` table) with overrides applied.

    Raises
    ------
    PipelineError
        An env without a recipe, an override out of range, or a condition that
        ``coach/conditions.toml`` does not define.
    RecipeError
        A malformed recipe.
    """
    path = default_recipe_path(env_id)
    if not path.is_file():
        raise PipelineError(
            f"env_id={env_id!r}: no recipe {path}; recipes exist for: {', '.join(recipe_envs())}",
            param="env_id",
        )
    base = load_pipeline_settings(path)
    checks = {"seeds": (seeds, 1, MAX_SEEDS), "steps": (steps, 1, MAX_STEPS),
              "roa_samples": (roa_samples, 1, MAX_SAMPLES),
              "episodes": (episodes, 0, MAX_EPISODES)}  # fmt: skip
    for name, (value, low, high) in checks.items():
        if value is not None:
            integer(value, name, PipelineError, low=low, high=high, param=name)
    if preset is not None and preset not in PRESETS:
        raise PipelineError(f"preset={preset!r}: expected one of {', '.join(PRESETS)}", param="preset")
    given: dict[str, Any] = {"seeds": seeds, "steps": steps, "preset": preset, "roa_samples": roa_samples,
                             "episodes": episodes, "condition": condition}  # fmt: skip
    settings = replace(base, **{k: v for k, v in given.items() if v is not None})
    check_settings(env_id, settings)
    return settings


def _preset_problem(env_id: str, preset: Any) -> str | None:
    """Why ``preset`` cannot tune a coach for ``env_id`` (its model card says), or None."""
    from pidlab.plant.card import find_card
    from pidlab.region.room import has_room_design

    card = find_card(env_id)
    if preset == "room" and card is not None and not has_room_design(card):
        return f"{env_id} has no linear design that measures its state (its coach is refined on the env)"
    if preset == "balance" and (card is None or card.balance is None):
        return f"{env_id}'s model card has no [balance] table (the balance preset poses a robot on its feet)"
    if preset == "room" and card is not None and card.refine_on_env:
        # the search on the env takes about 20 min, and the rescue stage's grid starts its probes
        # off the floor on a standing robot: the pipeline keeps the robust coach there
        return (
            f"on {env_id} the room preset searches the gains on the env; run it alone with "
            f"`pidlab tune {env_id} --auto --preset room` (the pipeline uses it on the pendulums only)"
        )
    return None


def check_settings(env_id: str, settings: PipelineSettings) -> None:
    """The settings can run on ``env_id``: its preset tunes a coach for it, its condition coaches.

    Checked before a pipeline writes anything, so a refusal leaves no folder behind that only
    these settings could resume.

    Raises
    ------
    PipelineError
        The preset does not apply to the env (``room`` on a contact-rich env), or the condition
        is unknown, trains no coach, has coaching fields the env's recipe rejects, or demonstrates
        for the whole budget.
    ModelCardError
        The env's model card cannot be read.
    """
    from pidlab.experiment.conditions import ConditionError

    problem = _preset_problem(env_id, settings.preset)
    if problem is not None:
        others = ", ".join(p for p in PRESETS if _preset_problem(env_id, p) is None)
        message = f"preset={settings.preset!r}: {problem}; expected one of {others}"
        raise PipelineError(message, param="preset")
    coaching_of(env_id, settings)
    try:
        coached = _coached_recipe(env_id, settings, load_recipe(default_recipe_path(env_id)))
    except ConditionError as exc:
        raise PipelineError(f"condition={settings.condition!r}: {exc}", param="condition") from None
    demos = coached.coaching.demonstrations
    if demos is not None and demos.steps >= settings.steps:
        raise PipelineError(
            f"steps={settings.steps}: the condition {settings.condition!r} has the coach demonstrate for "
            f"{demos.steps:,} env steps of the budget; expected more steps than that, or a condition without "
            "demonstrations (e.g. condition rescue-terminal)",
            param="steps",
        )


def coaching_of(env_id: str, settings: PipelineSettings) -> tuple[dict[str, Any], str]:
    """The ``coaching`` fields and description of the settings' condition on ``env_id``.

    The pipeline trains its own coach with them (the condition's coach and bounds do not apply).

    Raises
    ------
    PipelineError
        The condition is not in ``coach/conditions.toml``, or trains no coach.
    """
    from pidlab.experiment.conditions import conditions_path, load_conditions

    known = load_conditions()
    name = settings.condition
    if name not in known:
        raise PipelineError(
            f"condition={name!r}: not a condition of {conditions_path()}; expected one of {', '.join(known)}",
            param="condition",
        )
    c = known[name]
    if c.for_env(env_id).coach == "none":
        raise PipelineError(
            f"condition={name!r}: trains no coach; expected a coached condition", param="condition"
        )
    if c.for_env(env_id).algo is not None:
        raise PipelineError(
            f"condition={name!r}: names its own algorithm ({c.for_env(env_id).algo}); the main job trains "
            "the recipe's with and without the coach: expected a condition without algo",
            param="condition",
        )
    return dict(c.for_env(env_id).coaching), c.description


def _identity(env_id: str, settings: PipelineSettings) -> dict[str, Any]:
    # the coach-alone episodes are recomputed on every run: changing them needs no new folder
    kept = {k: v for k, v in asdict(settings).items() if k != "episodes"}
    return {"schema": PIPELINE_SCHEMA, "env_id": env_id, "settings": kept}


def _differences(old: Record, identity: dict[str, Any]) -> str:
    """What differs between a folder's pipeline and the one asked for, e.g. ``steps 1024 (now 2048)``."""
    was = old.identity or {}
    diffs = []
    if old.schema != PIPELINE_SCHEMA:
        diffs.append(f"schema {old.schema}")
    elif was.get("schema") != identity["schema"]:
        diffs.append(f"schema {was.get('schema')}")
    if was.get("env_id") != identity["env_id"]:
        diffs.append(f"env {was.get('env_id')}")
    for key, value in identity["settings"].items():
        before = was.get("settings", {}).get(key)
        if before != value:
            diffs.append(f"{key} {before} (now {value})")
    return ", ".join(diffs)


def _own_command(old: Record) -> str | None:
    """The command that made the pipeline ``old``, when it would resume it (else None)."""
    was = old.identity or {}
    kept = was.get("settings")
    settings: dict[str, Any] = kept if isinstance(kept, dict) else {}
    try:
        refused = _preset_problem(str(was.get("env_id")), settings.get("preset")) is not None
    except PidlabError:  # no card to say
        refused = True
    if refused or not old.command or old.schema != PIPELINE_SCHEMA:
        return None
    return shlex.join(old.command)


def _another(out: Path, old: Record, identity: dict[str, Any]) -> str:
    """The refusal of a folder that holds another pipeline: what differs, and commands that work."""
    own = _own_command(old)
    resume = f"Resume it with its own command ({own}), choose" if own else "Choose"
    return (
        f"out={out}: holds a pipeline run with other settings ({_differences(old, identity)}); nothing was "
        f"changed. {resume} another folder (--out), or remove this one (rm -r {shlex.quote(str(out))}) and "
        "run this command again"
    )


def check_out_folder(out: Path, identity: dict[str, Any]) -> Record | None:
    """The folder's existing record, if it holds this pipeline (nothing is written).

    Raises
    ------
    PipelineError
        The folder holds something else: another pipeline, or files that are not a pipeline's.
        The message names commands that work (another folder, or this one removed).
    """
    refusals = Refusals(
        not_a_folder=f"out={out}: exists and is not a folder",
        not_a_record=f"out={out}: pipeline.json is not a pipeline record; use another folder",
        not_ours=f"out={out}: not empty and holds no pipeline.json; choose another folder",
        another=lambda old: _another(out, old, identity),
    )
    return check_folder(out, "pipeline.json", PIPELINE_SCHEMA, identity, refusals, PipelineError, "out")


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
    records.append(StageRecord(name, "done", seconds, now()))
    say(f"[{index}/{len(STAGES)}] {name}: {seconds:.1f} s")


def _write_conditions(
    out: Path, coach_file: Path, coaching: dict[str, Any], condition: str, about: str
) -> Path:
    import tomli_w

    table = {
        "schema": "pidlab.conditions/1",
        "condition": {
            "none": {"description": "No coach: the recipe's agent alone (the baseline).", "coach": "none"},
            "coached": {
                "description": "The coach auto-tuned by this pipeline (coach.toml), with the regions "
                f"derived from it, intervening as the condition {condition!r} of coach/conditions.toml "
                f"says: {about}",
                "coach": str(coach_file.resolve()),
                "coaching": coaching,
            },
        },
    }
    header = "# Written by pidlab run: the two conditions it trains (see pidlab.experiment.conditions).\n"
    return atomic_write_text(out / "conditions.toml", header + tomli_w.dumps(table))


@dataclass(frozen=True)
class _Session:
    """What every stage of one pipeline session needs; ``stages`` grows as stages end."""

    env_id: str
    folder: Path
    settings: PipelineSettings
    loaded: LoadedModel
    progress_bar: bool
    say: Callable[[str], None]
    stages: list[StageRecord]
    workers: int | None = None

    def stage(self, name: str, done_before: bool = False) -> AbstractContextManager[None]:
        """Time stage ``name`` (or say it was done before) and record it."""
        return _stage(name, self.stages, done_before, self.say)


def _stage_file(path: Path, stage: str, read: Callable[[Path], Any]) -> None:
    """``read(path)`` when the file exists; a damaged one is refused, naming it and the stage."""
    if not path.exists():
        return
    try:
        data = read(path)
    except PidlabError as exc:
        raise PipelineError(f"{exc}; delete it to redo the {stage} stage") from None
    if data is None:
        raise PipelineError(f"{path}: damaged (not a JSON object); delete it to redo the {stage} stage")


def _check_stage_files(folder: Path) -> None:
    """The files of finished stages that a resumed pipeline reads back: each must read.

    Raises
    ------
    PipelineError
        A damaged file (named), with how to redo its stage.
    """
    from pidlab.controller.spec import load_spec
    from pidlab.experiment.sweep import EXPERIMENT_SCHEMA

    def json_object(path: Path) -> dict[str, Any] | None:
        data = load_json(path, "stage record", PipelineError)
        return data if isinstance(data, dict) else None

    _stage_file(folder / "tune.json", "tune", json_object)
    _stage_file(folder / "tuned.toml", "tune", load_spec)
    _stage_file(folder / "roa.json", "bounds", json_object)
    _stage_file(folder / "coach.toml", "bounds", load_spec)
    record = folder / "experiment" / "experiment.json"
    if record.exists():
        try:
            read_record(record, EXPERIMENT_SCHEMA, PipelineError)
        except PipelineError as exc:
            raise PipelineError(f"{exc}; move the folder {record.parent} away to train again") from None


def _check(
    env_id: str, out: str | Path, settings: PipelineSettings, workers: int | None
) -> tuple[Path, Record | None, Recipe, LoadedModel]:
    """Everything a pipeline session reads, checked before it writes anything.

    Returns the folder, its record (None: a new pipeline), the env's recipe and model.
    """
    from pidlab.experiment.sweep import check_finished_logs
    from pidlab.plant.model import load_model

    if workers is not None and (type(workers) is not int or workers < 1):
        raise PipelineError(f"workers={workers!r}: expected 1 or more", param="workers")
    folder = Path(out).resolve()
    check_settings(env_id, settings)  # before the folder: its refusal then names a command that works
    old = check_out_folder(folder, _identity(env_id, settings))
    recipe = load_recipe(default_recipe_path(env_id))
    loaded = load_model(env_id)
    loaded.require_card()
    _check_stage_files(folder)
    runs = folder / "experiment" / "runs" / env_id
    check_finished_logs(runs / c / f"seed-{seed}" for c in CONDITIONS for seed in range(settings.seeds))
    return folder, old, recipe, loaded


def _start(folder: Path, old: Record | None, env_id: str, settings: PipelineSettings, argv: Sequence[str],
           recipe: Recipe) -> Record:  # fmt: skip
    """Create the folder's figures folder and write (or extend, on resume) ``pipeline.json``."""
    try:
        (folder / "figures").mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PipelineError(f"out={folder}: cannot create the folder ({exc.strerror})", param="out") from None
    if old is None:
        identity = _identity(env_id, settings)
        record = new_record(PIPELINE_SCHEMA, argv, identity=identity, extra={"recipe": _shown(recipe.path)})
    else:
        record = add_resume(old, argv)
    write_record(folder / "pipeline.json", record)
    return record


def _linearize(s: _Session) -> tuple[Linearization, LtiReport]:
    """Stage 1 (seconds; the JSON is rewritten only when missing)."""
    from pidlab.linear.linearize import linearize
    from pidlab.linear.lti import analyze_lti
    from pidlab.linear.serialize import linearization_to_dict

    path = s.folder / "linearization.json"
    with s.stage("linearize"):
        lin = linearize(s.loaded)
        report_c, report_d = analyze_lti(lin.sys), analyze_lti(lin.sysd)
        if not path.exists():
            write_json(path, linearization_to_dict(lin, report_c, report_d))
    return lin, report_c


def _tune(s: _Session, lin: Linearization) -> tuple[CoachSpec, dict[str, Any], Path]:
    """Stage 2: the auto-tuned spec, what was asked and achieved, and its file."""
    from tqdm.auto import tqdm

    from pidlab.controller.autotune import tune
    from pidlab.controller.spec import load_spec, save_spec
    from pidlab.report.pipeline import tune_summary

    tuned_path, tune_json = s.folder / "tuned.toml", s.folder / "tune.json"
    done = tuned_path.exists() and tune_json.exists()
    with s.stage("tune", done):
        if not done:
            desc = f"tuning ({s.settings.preset})"
            with tqdm(desc=desc, unit="eval", disable=not s.progress_bar) as bar:

                def tick(n: int) -> None:
                    bar.update(n - bar.n)

                if s.settings.preset == "room":
                    from pidlab.region.room import tune_for_room

                    result = tune_for_room(s.loaded, lin=lin, workers=s.workers, progress=tick)
                elif s.settings.preset == "balance":
                    from pidlab.controller.balance import tune_balance

                    result = tune_balance(s.loaded)
                else:
                    result = tune(s.loaded, preset=s.settings.preset, lin=lin, progress=tick)
            write_json(tune_json, tune_summary(result))
            save_spec(result.spec, tuned_path)
    return load_spec(tuned_path), read_json(tune_json), tuned_path


def _analyze(
    s: _Session, spec: CoachSpec, tuned_path: Path
) -> tuple[CoachAnalysis, list[Path], CoachScore | None]:
    """Stage 3 (fast and deterministic: recomputed each time, so the report always matches the code)."""
    from tqdm.auto import tqdm

    from pidlab.controller.analysis import analyze_coach
    from pidlab.controller.balance import design_linearization
    from pidlab.controller.pid import Coach
    from pidlab.controller.rollout import coach_alone
    from pidlab.report.plots import write_plots

    with s.stage("analyze"):
        coach = Coach(spec, s.loaded)
        analysis = analyze_coach(coach, s.loaded, design_linearization(spec, s.loaded))
        if not analysis.stable:
            unstable = f"{s.env_id}: the auto-tuned coach's closed loop is unstable; see {tuned_path}"
            raise PipelineError(unstable)
        written = write_plots(analysis, coach, s.folder / "figures")
        score = None
        if s.settings.episodes:
            with tqdm(total=1, desc="coach alone", unit="run", disable=not s.progress_bar) as bar:
                score = coach_alone(spec, s.loaded, episodes=s.settings.episodes)
                bar.update(1)
    return analysis, written, score


def _region(
    s: _Session, spec: CoachSpec, pair: tuple[str, str]
) -> tuple[RegionOfAttraction, list[Any], CriticalBounds]:
    """The certified region (with trajectories to draw) and the bounds derived from it."""
    from tqdm.auto import tqdm

    from pidlab.region.bounds import derive_bounds
    from pidlab.region.roa import estimate_roa

    with tqdm(total=100, desc="region", unit="%", disable=not s.progress_bar) as bar:
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
            spec, s.loaded, samples=s.settings.roa_samples, seed=0, keep_trajectories=80,
            record=pair if pair[0] != pair[1] else None, progress=roa_progress,
        )  # fmt: skip
        bar.set_description_str("region: deriving the critical bounds")
        bar.n = 0
        bar.refresh()
        crit = derive_bounds(region, spec, s.loaded, seed=0)
        bar.n = 100
        bar.refresh()
    return region, kept, crit


def _coached_recipe(env_id: str, settings: PipelineSettings, recipe: Recipe) -> Recipe:
    """The recipe as the coached runs train it: its ``[coaching]`` with the settings' condition's fields."""
    from pidlab.experiment.conditions import with_coaching

    fields = coaching_of(env_id, settings)[0]
    return with_coaching(recipe, fields, f"condition {settings.condition} on {env_id}")


def _rescue(
    s: _Session, spec: CoachSpec, units: dict[str, str], png: Path
) -> tuple[CoachSpec, dict[str, Any]]:
    """The coach with its rescue region as takeover region, the region's facts, and its figure."""
    from tqdm.auto import tqdm

    from pidlab.files import save_figure
    from pidlab.region.rescue import default_settings, estimate_rescue, with_rescue
    from pidlab.report.pipeline import rescue_summary
    from pidlab.report.plots import plot_rescue_region

    with tqdm(total=100, desc="rescue region", unit="%", disable=not s.progress_bar) as bar:

        def progress(stage: str, fraction: float | None) -> None:
            bar.set_description_str(f"rescue region: {stage}"[:60])
            bar.n = int(100 * (fraction or 0.0))
            bar.refresh()

        journal = s.folder / RESCUE_JOURNAL
        settings = default_settings(spec, s.loaded)
        region = estimate_rescue(spec, s.loaded, settings, s.workers, progress, journal)
    coached = with_rescue(spec, region)
    title = f"{spec.env_id} / {spec.name}"
    save_figure(plot_rescue_region(region.grid, coached.bounds, units, title), png)
    return coached, rescue_summary(region)


def _bounds(
    s: _Session, spec: CoachSpec, units: dict[str, str], region_kind: str
) -> tuple[CoachSpec, dict[str, Any], Path, Path]:
    """Stage 4: the coach with its bounds, the region's facts, the coach's file and the region figure.

    With ``region_kind == "rescue"`` the coach's rescue region (:mod:`pidlab.region.rescue`) is
    estimated after its certified core and becomes its takeover region (figure ``rescue.png``).
    Redone when the tuned coach or the region kind changed since (``roa.json`` records both).
    """
    from pidlab.controller.spec import load_spec, save_spec
    from pidlab.files import save_figure
    from pidlab.region.bounds import with_bounds
    from pidlab.region.journal import drop_journal
    from pidlab.report.pipeline import roa_summary
    from pidlab.report.plots import plot_roa_slice
    from pidlab.rl.rundir import spec_digest

    coach_path, roa_json = s.folder / "coach.toml", s.folder / "roa.json"
    roa_png, rescue_png = s.folder / "figures" / "roa.png", s.folder / "figures" / "rescue.png"
    lp0 = spec.loops[0]
    pair = (lp0.signal, lp0.rate_signal or lp0.signal)
    tuned_digest = spec_digest(spec)
    rescue = region_kind == "rescue"
    facts = read_json(roa_json) if roa_json.exists() else {}
    done = (
        coach_path.exists()
        and roa_png.exists()
        and facts.get("tuned_sha256") == tuned_digest
        and ("rescue" in facts) == rescue
        and (rescue_png.exists() or not rescue)
    )
    with s.stage("bounds", done):
        if not done:
            region, kept, crit = _region(s, spec, pair)
            save_figure(plot_roa_slice(region, pair, kept, units, bounds=crit), roa_png)
            coached, facts = (
                with_bounds(spec, crit),
                {**roa_summary(region, crit, pair), "tuned_sha256": tuned_digest},
            )
            if rescue:
                coached, facts["rescue"] = _rescue(s, coached, units, rescue_png)
            save_spec(coached, coach_path)
            write_json(roa_json, facts)
            drop_journal(s.folder / RESCUE_JOURNAL)  # its outcomes are in coach.toml
    return load_spec(coach_path), read_json(roa_json), coach_path, roa_png


def _train(
    s: _Session, coach_path: Path, workers: int | None, argv: Sequence[str]
) -> tuple[Plan, SweepResult]:
    """Stage 5: train with and without the coach (a resumable sweep in ``experiment/``)."""
    from pidlab.experiment.sweep import plan, run_sweep

    coaching, about = coaching_of(s.env_id, s.settings)
    conditions = _write_conditions(s.folder, coach_path, coaching, s.settings.condition, about)
    sweep_plan = plan(
        [s.env_id], list(CONDITIONS), list(range(s.settings.seeds)), s.folder / "experiment",
        conditions_file=conditions, steps=s.settings.steps,
    )  # fmt: skip
    with s.stage("train"):
        sweep = run_sweep(sweep_plan, workers=workers, argv=argv, progress_bar=s.progress_bar)
    return sweep_plan, sweep


@dataclass(frozen=True)
class _Made:
    """What stages 1-4 made, for the report."""

    recipe: Recipe
    lin: Linearization
    lti: LtiReport
    tuning: dict[str, Any]
    analysis: CoachAnalysis
    figures: list[Path]
    score: CoachScore | None
    coached: CoachSpec
    roa: dict[str, Any]
    roa_png: Path
    units: dict[str, str]


def published_evidence(env_id: str, condition: str) -> Evidence | None:
    """The published experiment that compares ``condition`` with ``none`` on ``env_id``.

    Read from ``docs/results/*/summary.csv`` of a source checkout: among the folders that ran
    the analysis plan's confirmatory seeds for their conditions, one that trained ``condition``'s
    runs itself before one that copied them from an earlier sweep (``reused.json``), then the one
    with the fewest conditions (the smallest Holm family), the last in name order among equals;
    else the last such pilot folder; else None.
    """
    import csv

    from pidlab.experiment.plan import role
    from pidlab.files import read_json
    from pidlab.report.pipeline import EVIDENCE_METRICS, Evidence

    root = source_root()
    if root is None:
        return None
    found: dict[str, tuple[tuple[int, int], Evidence]] = {}
    for path in sorted((root / "docs" / "results").glob("*/summary.csv")):
        with open(path, newline="") as f:
            rows = {(r["condition"], r["metric"]): r for r in csv.DictReader(f) if r.get("env") == env_id}
        if all((c, m) in rows for c in ("none", condition) for m in EVIDENCE_METRICS):
            kept = {k: v for k, v in rows.items() if k[0] in ("none", condition) and k[1] in EVIDENCE_METRICS}
            exp = path.parent / "experiment.json"
            record = read_json(exp) if exp.exists() else {}
            identity = record.get("identity", {}) if isinstance(record, dict) else {}
            seeds, conds = identity.get("seeds", []), identity.get("conditions", [])
            envs = identity.get("envs", [env_id])
            kind = role(
                seeds, conds, _algorithms(path.parent, identity), envs if isinstance(envs, list) else [env_id]
            )
            copied = _copied(path.parent, env_id, condition)
            size = (int(copied), len(conds) if kind == "confirmatory" else 0)
            if kind not in found or size <= found[kind][0]:
                found[kind] = (size, Evidence(f"docs/results/{path.parent.name}", kept))
    best = found.get("confirmatory", found.get("pilot", found.get("exploratory")))
    return None if best is None else best[1]


def _copied(folder: Path, env_id: str, condition: str) -> bool:
    """Whether every published run of ``condition`` in ``folder`` was copied from an earlier sweep."""
    from pidlab.experiment.reuse import REUSED_NAME

    runs = list((folder / "runs" / env_id / condition).glob("seed-*"))
    return bool(runs) and all((run / REUSED_NAME).exists() for run in runs)


def _algorithms(folder: Path, identity: dict[str, Any]) -> tuple[str, ...]:
    """The algorithms a published experiment's runs trained (every run's config, each condition's own)."""
    from pidlab.experiment.analysis import run_algorithms

    envs, conditions = identity.get("envs", []), identity.get("conditions", [])
    if not isinstance(envs, list) or not isinstance(conditions, list):
        return ("ppo",)  # an unreadable record: no evidence of another agent
    return run_algorithms(folder, [str(e) for e in envs], [str(c) for c in conditions]) or ("ppo",)


def _report(s: _Session, record: Record, made: _Made, sweep_plan: Plan) -> tuple[Path, Path]:
    """Stage 6: the experiment's own report, the learning curves and the pipeline's report."""
    from pidlab.experiment.analysis import analyze
    from pidlab.experiment.sweep import lock_experiment
    from pidlab.files import save_figure
    from pidlab.report.curves import plot_learning_curves
    from pidlab.report.experiment import render_html, write_report
    from pidlab.report.pipeline import PipelineFacts, render_markdown

    folder, env_id = s.folder, s.env_id
    with s.stage("report"):
        exp_record = read_json(sweep_plan.out / "experiment.json")
        results = analyze(exp_record["identity"], sweep_plan.out, sweep_plan.recipes)
        with lock_experiment(sweep_plan):
            write_report(sweep_plan, progress_bar=False, analysis=results)
        curves = folder / "figures" / "learning-curves.png"
        if (env_id, "none") in results.cells or (env_id, "coached") in results.cells:
            save_figure(plot_learning_curves(results, env_id), curves)
        _finish_record(folder, record, s.stages)
        facts = PipelineFacts(
            env_id=env_id,
            settings=s.settings,
            record=read_json(folder / "pipeline.json"),
            coaching=recipe_to_dict(_coached_recipe(env_id, s.settings, made.recipe))["coaching"],
            lti=made.lti,
            control_dt=float(made.lin.control_dt),
            tuning=made.tuning,
            spec=made.coached,
            analysis=made.analysis,
            score=made.score,
            roa=made.roa,
            units=made.units,
            results=results,
            figures=tuple(p.relative_to(folder).as_posix() for p in made.figures),
            roa_figure=made.roa_png.relative_to(folder).as_posix(),
            curves_figure=curves.relative_to(folder).as_posix() if curves.exists() else None,
            evidence=published_evidence(env_id, s.settings.condition),
        )
        text = render_markdown(facts)
        md = atomic_write_text(folder / "report.md", text)
        page = atomic_write_text(folder / "report.html", render_html(text, f"pidlab run {env_id}"))
    return md, page


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
    path_argument(out, "out", PipelineError, what="the pipeline's folder")
    folder = _check(env_id, out, settings, workers)[0]  # refused here, nothing is made
    with hold_lock(folder, PipelineError, param="out"):
        folder, old, recipe, loaded = _check(env_id, out, settings, workers)  # again, under the lock
        record = _start(folder, old, env_id, settings, argv, recipe)
        return _stages(
            _Session(env_id, folder, settings, loaded, progress_bar, say, [], workers),
            record,
            recipe,
            workers,
            argv,
        )


def _stages(
    s: _Session, record: Record, recipe: Recipe, workers: int | None, argv: Sequence[str]
) -> PipelineResult:
    """The six stages of one session, after its record was written."""
    folder = s.folder
    units = {v.name: v.unit for v in s.loaded.require_card().observation}
    try:
        lin, lti = _linearize(s)
        spec, tuning, tuned_path = _tune(s, lin)
        analysis, figures, score = _analyze(s, spec, tuned_path)
        region_kind = _coached_recipe(s.env_id, s.settings, recipe).coaching.region
        coached, roa, coach_path, roa_png = _bounds(s, spec, units, region_kind)
    except KeyboardInterrupt:  # the stages that finished keep their times
        _finish_record(folder, record, s.stages)
        raise
    sweep_plan, sweep = _train(s, coach_path, workers, argv)
    failed = sweep.count("failed")
    if sweep.interrupted:
        s.stages[-1] = replace(s.stages[-1], status="interrupted")
        _finish_record(folder, record, s.stages)
        md, page = folder / "report.md", folder / "report.html"
        return PipelineResult(folder, md, page, tuple(s.stages), True, failed)
    made = _Made(recipe, lin, lti, tuning, analysis, figures, score, coached, roa, roa_png, units)
    md, page = _report(s, record, made, sweep_plan)
    _finish_record(folder, record, s.stages)
    return PipelineResult(folder, md, page, tuple(s.stages), False, failed)


def _shown(path: str | None) -> str:
    """A path as the report shows it: relative to pidlab's source tree when inside it."""
    root = source_root()
    p = Path(path or "").resolve()
    return p.relative_to(root).as_posix() if root is not None and p.is_relative_to(root) else str(p)


def with_stage_times(record: Record, stages: Sequence[StageRecord]) -> Record:
    """``record`` (as this session started) with the times of ``stages`` added.

    Each stage keeps the time of its last run; training is summed over the sessions that trained
    (a resumed sweep only trains what was left): an interrupted session's training time waits in
    ``pending_train_s`` for the session that finishes it.
    """
    times = dict(record.extra.get("stages", {}))
    pending = dict(record.extra.get("pending_train_s", {}))
    for r in stages:
        if r.name == "train" and r.status in ("done", "interrupted"):
            total = float(pending.get("seconds", 0.0)) + r.seconds
            if r.status == "interrupted":
                pending = {"seconds": round(total, 2)}
                continue
            pending = {}
            times[r.name] = {"seconds": round(total, 2), "at": r.at}
        elif r.status == "done":
            times[r.name] = {"seconds": round(r.seconds, 2), "at": r.at}
    return record.with_extra(stages=times, pending_train_s=pending or None)


def _finish_record(folder: Path, record: Record, stages: Sequence[StageRecord]) -> None:
    """Write the stage times into ``pipeline.json`` (``record`` is the session's start)."""
    write_record(folder / "pipeline.json", with_stage_times(record, stages))
