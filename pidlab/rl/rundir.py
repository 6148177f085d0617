"""Run directories: what a training run writes, how it is read back, and how it is cut back on resume.

A run directory holds ``config.toml`` (the resolved recipe and the coach's name, source and
digest), ``coach.toml`` (the spec), ``run.json`` (seed, command, versions, git SHA, resumes: a
:class:`pidlab.provenance.Record`), ``episodes.csv``, ``evaluations.csv``, ``tb/``,
``checkpoints/<env steps>/`` (the latest two) and, once the budget is spent, ``final_model.zip``,
``final_vecnormalize.npz`` and ``summary.json``. See :mod:`pidlab.rl.train`.

Everything read back from a run directory may have been damaged since (a disk that filled up, a
hand edit, a copy cut short): each reader here says which file is damaged, in one line.
"""

from __future__ import annotations

import csv
import io
import os
import sys
import weakref
from pathlib import Path
from typing import Any

import tomli_w

from pidlab.checks import path_under
from pidlab.controller.spec import CoachSpec, dumps_spec, loads_spec
from pidlab.errors import CheckpointError, PidlabError, RunDirError
from pidlab.files import atomic_write_text, load_json, make_folder, read_text, read_toml
from pidlab.provenance import (
    Refusals,
    add_resume,
    check_folder,
    digest,
    new_record,
    read_record,
    write_record,
)
from pidlab.rl.recipe import ALGOS, Recipe, parse_recipe, recipe_to_dict

EPISODE_COLUMNS = (
    "episode",
    "env_steps_so_far",
    "agent_steps_so_far",
    "agent_steps",
    "coach_steps",
    "interventions",
    "agent_return",
    "total_return",
    "terminated",
    "env_index",
    "env_end",
    "fell",
    "runs",
    "longest_run",
)
"""One row per ended *agent* episode. ``terminated``: the agent's episode ended as terminated (a
fall, or a ``terminal``-view takeover); ``env_end``: the env's episode ended with it (0: a
``terminal``-view rescue handed the running env to the next agent episode); ``fell``: the env
terminated (a fall, whoever was acting); ``runs`` and ``longest_run``: the agent's uninterrupted
runs of actions in the episode (see :mod:`pidlab.rl.coaching`), ``nan`` in logs written before
pidlab counted them."""
LEGACY_EPISODE_COLUMNS = EPISODE_COLUMNS[:-4]
"""``episodes.csv`` as pidlab wrote it before agent and env episodes were told apart: every episode
ended the env's, and ``terminated`` was the env's. Such a log is read with ``env_end = 1`` and
``fell = terminated`` (a resume rewrites it so)."""
RUNLESS_EPISODE_COLUMNS = EPISODE_COLUMNS[:-2]
"""``episodes.csv`` as pidlab wrote it before it counted the agent's uninterrupted runs: read with
``runs`` and ``longest_run`` unknown (``nan``)."""
TIMING_COLUMNS = ("env_steps_so_far", "wall_s")
"""``timing.csv``: the wall-clock seconds since the run started (all its sessions, demonstrations,
cloning and evaluations included) at each evaluation. Kept apart from ``evaluations.csv``, which
the same seed reproduces exactly; wall-clock time never repeats."""
EVALUATION_COLUMNS = (
    "env_steps_so_far",
    "agent_steps_so_far",
    "episodes_so_far",
    "mean_return",
    "std_return",
    "min_return",
    "max_return",
    "mean_length",
    "returns",
)


def _csv_text(columns: tuple[str, ...], rows: list[list[str]]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(columns)
    w.writerows(rows)
    return buf.getvalue()


def read_csv_rows(path: Path) -> list[dict[str, str]]:
    """Rows of a run's CSV file as dicts (header keys)."""
    if not path.exists():
        return []
    return list(csv.DictReader(io.StringIO(read_text(path, "run log", RunDirError), newline="")))


def read_csv_table(path: Path) -> tuple[list[str], list[list[str]]]:
    """A run's CSV file as its header and rows, blank lines skipped (([], []) when absent or empty)."""
    if not path.exists():
        return [], []
    reader = csv.reader(io.StringIO(read_text(path, "run log", RunDirError), newline=""))
    header = next(reader, [])
    return header, [row for row in reader if row]


def csv_columns(header: list[str], rows: list[list[str]], name: str) -> dict[str, tuple[str, ...]]:
    """The rows of CSV file ``name`` by column: header name -> the column's values.

    The rows :func:`read_csv_rows` reads, held by column: a log of many thousand episodes is read
    in a fraction of the time.

    Raises
    ------
    ValueError
        A row whose number of fields differs from the header's.
    """
    ragged = next((i for i, row in enumerate(rows, 1) if len(row) != len(header)), None)
    if ragged is not None:
        raise ValueError(f"{name}: row {ragged} has {len(rows[ragged - 1])} fields, expected {len(header)}")
    return dict(zip(header, zip(*rows, strict=True) if rows else [()] * len(header), strict=True))


def _row_problem(row: list[str], columns: tuple[str, ...], index: int) -> str | None:
    """Why ``row`` (data row ``index``) is not one pidlab wrote, or None."""
    if len(row) != len(columns):
        return f"{len(row)} fields, expected {len(columns)}"
    for name, value in zip(columns, row, strict=True):
        try:
            for part in value.split(";") if name == "returns" else [value]:
                float(part)
        except ValueError:
            return f"{name} = {value[:40]!r} is not a number"
    if columns[0] == "episode" and row[0] != str(index):
        return f"episode {row[0][:40]!r}, expected {index}"
    return None


def _upgrade_legacy(rows: list[list[str]], written: tuple[str, ...]) -> list[list[str]]:
    """Rows of an older ``episodes.csv`` in today's columns (see :data:`LEGACY_EPISODE_COLUMNS`)."""
    if written == LEGACY_EPISODE_COLUMNS:
        terminated = LEGACY_EPISODE_COLUMNS.index("terminated")
        rows = [[*row, "1", row[terminated]] for row in rows]
    return [[*row, "nan", "nan"] for row in rows]


def _written_columns(columns: tuple[str, ...], header: tuple[str, ...]) -> tuple[str, ...]:
    """The columns a log was written in: today's, or an older ``episodes.csv``'s that is read upgraded."""
    if columns == EPISODE_COLUMNS and header in (LEGACY_EPISODE_COLUMNS, RUNLESS_EPISODE_COLUMNS):
        return header
    return columns


def check_log(path: Path, columns: tuple[str, ...], keep: int) -> list[list[str]]:
    """The first ``keep`` rows of a run's CSV log, checked: what a checkpoint recorded is there.

    Rows after the first ``keep`` are not read (a row cut by a kill is harmless there). An
    ``episodes.csv`` with the legacy header (:data:`LEGACY_EPISODE_COLUMNS`) is read and its rows
    returned in today's columns.

    Raises
    ------
    CheckpointError
        The file is missing, not text, has another header, a damaged row among the first
        ``keep``, or fewer rows than that; the message names it.
    """
    if keep == 0:
        return []  # nothing recorded, nothing to check
    if not path.exists():
        raise CheckpointError(f"{path}: missing; the checkpoint recorded {keep} rows")
    lines = read_text(path, "run log", CheckpointError).splitlines()
    try:
        parsed = list(csv.reader(lines[: keep + 1]))
    except csv.Error as exc:
        raise CheckpointError(f"{path}: damaged ({exc})") from None
    written = _written_columns(columns, tuple(parsed[0])) if parsed else columns
    if not parsed or tuple(parsed[0]) != written:
        raise CheckpointError(f"{path}: damaged (its first line is not the header {','.join(columns)})")
    rows = parsed[1:]
    for i, row in enumerate(rows):
        problem = _row_problem(row, written, i)
        if problem is not None:
            raise CheckpointError(
                f"{path}: row {i + 1} is damaged ({problem}); the checkpoint recorded {keep}"
            )
    if len(rows) < keep:
        raise CheckpointError(f"{path}: holds {len(rows)} complete rows, the checkpoint recorded {keep}")
    return _upgrade_legacy(rows, written) if written != columns else rows


def truncate_csv(path: Path, columns: tuple[str, ...], keep: int) -> None:
    """Keep the header and the first ``keep`` rows of a run's CSV file (checked; written atomically).

    A legacy ``episodes.csv`` is rewritten in today's columns (see :data:`LEGACY_EPISODE_COLUMNS`).

    Raises
    ------
    CheckpointError
        As :func:`check_log`; nothing is written then.
    """
    atomic_write_text(path, _csv_text(columns, check_log(path, columns, keep)))


def truncate_timing(path: Path, env_steps: int) -> None:
    """Keep ``timing.csv``'s rows up to ``env_steps`` (a resume's checkpoint); damaged rows go.

    Timing is not part of what a checkpoint vouches for: a missing file stays missing.
    """
    if not path.is_file():
        return
    kept = []
    for row in read_csv_rows(path):
        try:
            step, wall = int(row.get("env_steps_so_far") or ""), float(row.get("wall_s") or "")
        except ValueError:
            continue
        if step <= env_steps:
            kept.append([str(step), repr(wall)])
    atomic_write_text(path, _csv_text(TIMING_COLUMNS, kept))


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, bool):
        return str(int(value))
    return str(value)


class CsvLog:
    """Append-only CSV with a flush per row (the checkpoint fsyncs)."""

    def __init__(self, path: Path, columns: tuple[str, ...]) -> None:
        if not path.exists():
            atomic_write_text(path, _csv_text(columns, []))
        self.fh = open(path, "a", newline="", encoding="utf-8")
        self.writer = csv.writer(self.fh, lineterminator="\n")

    def write(self, row: list[Any]) -> None:
        """Append one row and flush it."""
        self.writer.writerow([_fmt(v) for v in row])
        self.fh.flush()

    def sync(self) -> None:
        """Flush and fsync (a checkpoint then records how many rows exist)."""
        self.fh.flush()
        os.fsync(self.fh.fileno())

    def close(self) -> None:
        """Close the file."""
        self.fh.close()


def is_checkpoint_name(name: str) -> bool:
    """Whether ``name`` is a checkpoint folder's (its env steps, 12 digits)."""
    return len(name) == 12 and name.isascii() and name.isdigit()


def checkpoint_folders(run_dir: Path, complete: bool = True) -> list[Path]:
    """The run's checkpoints, oldest first: those with ``state.json``, or (``complete`` False) all.

    A checkpoint is written into a temporary folder and renamed into place once complete, so a
    numbered folder without ``state.json`` was damaged since; a resume reports it as such.
    """
    folder = run_dir / "checkpoints"
    if not folder.is_dir():
        return []
    return sorted(
        p
        for p in folder.iterdir()
        if is_checkpoint_name(p.name) and p.is_dir() and (not complete or (p / "state.json").exists())
    )


def latest_checkpoint(run_dir: Path) -> Path | None:
    """The newest complete checkpoint folder (one with ``state.json``), or None."""
    done = checkpoint_folders(run_dir)
    return done[-1] if done else None


STATE_KEYS = ("env_steps", "agent_steps", "coach_steps", "interventions", "episodes", "evaluations",
              "next_evaluation", "next_checkpoint", "resumes", "num_timesteps", "policy_updates",
              "env_episodes", "env_resets", "falls", "rollin_stage", "kept_rounds", "kept_at",
              "value_vetoes", "proposals_taken")  # fmt: skip
"""The counters a checkpoint's ``state.json`` holds (``pidlab.rl.train.Counters`` and SB3's)."""
LATER_KEYS = (
    "policy_updates",
    "env_episodes",
    "env_resets",
    "falls",
    "rollin_stage",
    "kept_rounds",
    "kept_at",
    "value_vetoes",
    "proposals_taken",
)
"""Counters that checkpoints written by earlier versions of pidlab lack (the trainer derives them)."""


def read_state(checkpoint: Path) -> dict[str, int]:
    """A checkpoint's ``state.json``, checked: non-negative integer counters that agree.

    Raises
    ------
    CheckpointError
        The file is missing, damaged (cut short, not JSON), or its counters are not what a
        checkpoint records (missing, not integers, ``env_steps`` not agent + coach steps, or not
        the folder's name); the message names it.
    """
    path = checkpoint / "state.json"
    data = load_json(path, "checkpoint state", CheckpointError)
    if not isinstance(data, dict):
        raise CheckpointError(f"{path}: damaged (not a JSON object)")
    state: dict[str, int] = {}
    for key in STATE_KEYS:
        if key in LATER_KEYS and key not in data:
            continue  # a checkpoint from before pidlab counted them: the trainer derives them
        value = data.get(key, 0)
        if type(value) is not int or value < 0:
            raise CheckpointError(f"{path}: damaged ({key} = {value!r}, expected an integer >= 0)")
        state[key] = value
    for key in ("env_steps", "episodes", "evaluations", "num_timesteps"):
        if key not in data:
            raise CheckpointError(f"{path}: damaged (no {key})")
    if "agent_steps" in data and state["env_steps"] != state["agent_steps"] + state["coach_steps"]:
        raise CheckpointError(f"{path}: damaged (env_steps is not agent_steps + coach_steps)")
    if is_checkpoint_name(checkpoint.name) and int(checkpoint.name) != state["env_steps"]:
        raise CheckpointError(f"{path}: damaged (env_steps {state['env_steps']} in folder {checkpoint.name})")
    return state


_DIGESTS: dict[int, tuple[weakref.ref[CoachSpec], str]] = {}
""":func:`spec_digest` per spec object alive (its id, a weak reference to it, the digest)."""


def spec_digest(spec: CoachSpec) -> str:
    """SHA-256 of the spec's canonical text (what a run was coached by).

    Remembered while the spec object lives (a spec is immutable): a rescue region's spec takes a
    tenth of a second to write out, and planning a sweep asks for every run's coach.
    """
    held = _DIGESTS.get(id(spec))
    if held is not None and held[0]() is spec:
        return held[1]
    value = digest(dumps_spec(spec))
    key = id(spec)
    _DIGESTS[key] = (weakref.ref(spec, lambda _: _DIGESTS.pop(key, None)), value)
    return value


_RUN_SPECS: dict[str, CoachSpec] = {}
"""The coach specs of the runs read last, by their text: the runs of a sweep share a few."""


def _run_spec(text: str, where: str) -> CoachSpec:
    """The spec a run's ``coach.toml`` holds (``text``), parsed once per text (errors name ``where``)."""
    spec = _RUN_SPECS.get(text)
    if spec is None:
        spec = loads_spec(text, where)
        if len(_RUN_SPECS) >= 8:
            _RUN_SPECS.pop(next(iter(_RUN_SPECS)))
        _RUN_SPECS[text] = spec
    return spec


def config_dict(recipe: Recipe, spec: CoachSpec | None, coach_source: str | None) -> dict[str, Any]:
    """The tables of ``config.toml``: the resolved recipe and which coach (name, source, SHA-256).

    Sources are named as :func:`pidlab.data.portable_name` does (``tuning/ENV.NAME.toml``), never
    by the writer's absolute path; the spec's SHA-256 identifies it wherever it came from.
    """
    from pidlab.data import portable_name

    coach: dict[str, Any] = {"name": "none"}
    if spec is not None:
        coach = {"name": spec.name, "source": portable_name(coach_source or ""), "sha256": spec_digest(spec)}
    return {
        "schema": "pidlab.run-config/1",
        "env_id": recipe.env_id,
        "recipe_source": portable_name(recipe.path or ""),
        "coach": coach,
        "recipe": recipe_to_dict(recipe),
    }


def run_settings(recipe: Recipe, spec: CoachSpec | None) -> dict[str, Any]:
    """What a run does, as data: :func:`config_dict` less what does not change it.

    Not the recipe's file or the coach spec's file (the spec's SHA-256 identifies the coach), and
    of the recipe's algorithm tables only the one the run trains with: a change to another
    algorithm's table changes no run of this one.
    """
    settings = config_dict(recipe, spec, None)
    settings.pop("recipe_source", None)
    settings["coach"].pop("source", None)
    tables = settings["recipe"]
    for algo in ALGOS:
        if algo != recipe.algo:
            tables.pop(algo, None)
    return settings


def settings_digest(recipe: Recipe, spec: CoachSpec | None) -> str:
    """The digest of :func:`run_settings` (16 hex digits): two runs with the same one train alike."""
    return digest(run_settings(recipe, spec), 16)


def stored_settings_digest(run_dir: str | Path) -> str | None:
    """:func:`settings_digest` of what a run folder's ``config.toml`` records (None: nothing readable)."""
    if not (Path(run_dir) / "config.toml").is_file():
        return None
    try:
        recipe, spec, _ = load_run_config(run_dir)
    except PidlabError:
        return None
    return settings_digest(recipe, spec)


def load_run_config(run_dir: str | Path) -> tuple[Recipe, CoachSpec | None, dict[str, Any]]:
    """The resolved recipe and coach spec a run directory was started with.

    Raises
    ------
    RunDirError
        Not a run directory, or its ``config.toml`` / ``coach.toml`` is damaged (the message
        names the file).
    RecipeError, SpecError
        The recipe or spec in it is malformed.
    """
    run_dir = Path(run_dir)
    path = run_dir / "config.toml"
    if not path.is_file():
        raise RunDirError(f"{run_dir}: not a pidlab run directory (no config.toml)")
    config = read_toml(path, "run config", RunDirError)
    table, coach = config.get("recipe"), config.get("coach", {"name": "none"})
    if not isinstance(table, dict):
        raise RunDirError(f"{path}: damaged (no [recipe] table; pidlab writes one in every run's config)")
    if not isinstance(coach, dict) or not isinstance(coach.get("name", "none"), str):
        raise RunDirError(f"{path}: damaged ([coach] is not a table with a name)")
    recipe = parse_recipe(table, f"{path}:recipe")
    spec_path = run_dir / "coach.toml"
    coached = coach.get("name", "none") != "none"
    if coached and not spec_path.is_file():
        raise RunDirError(f"{spec_path}: missing; the run was coached by {coach['name']!r} (see {path})")
    if "coach" in config and not coached and spec_path.exists():
        raise RunDirError(
            f"{spec_path}: the run was not coached (see {path}); remove the file or start a new run"
        )
    spec = None
    if spec_path.exists():
        spec = _run_spec(read_text(spec_path, "run's coach spec", RunDirError), str(spec_path))
    return recipe, spec, config


def default_run_dir(recipe: Recipe, spec: CoachSpec | None, root: str | Path = "runs") -> Path:
    """``runs/<env>/<coach>-<algo>-seed<seed>``, checked to stay under ``root``.

    Raises
    ------
    RunDirError
        The env id or the spec's name would leave ``root`` (see :func:`pidlab.checks.path_under`).
    """
    coach = spec.name if spec is not None else "none"
    return path_under(root, recipe.env_id, f"{coach}-{recipe.algo}-seed{recipe.seed}", error=RunDirError)


RUN_SCHEMA = "pidlab.run/1"


def _refusals(run_dir: Path) -> Refusals:
    taken = f"{run_dir} exists and is not empty; resume it with --resume {run_dir}, or choose --run-dir"
    return Refusals(
        not_a_folder=f"{run_dir} exists and is not a folder; choose another --run-dir",
        not_a_record=taken,
        not_ours=taken,
        another=lambda _record: taken,
    )


def check_new_run_dir(run_dir: Path) -> None:
    """Refuse a ``run_dir`` that cannot hold a new run (nothing is written).

    Raises
    ------
    RunDirError
        ``run_dir`` exists and is not empty, or is a file.
    OutputError
        ``run_dir`` cannot be created or written.
    """
    refusals = _refusals(run_dir)
    if check_folder(run_dir, "run.json", RUN_SCHEMA, None, refusals, RunDirError, "run_dir") is not None:
        raise RunDirError(refusals.not_ours)  # a run is resumed with resume(), never started again


def prepare_run_dir(
    run_dir: Path, recipe: Recipe, spec: CoachSpec | None, coach_source: str | None, argv: list[str] | None
) -> None:
    """Create a new run directory with ``config.toml``, ``coach.toml`` and ``run.json``.

    Raises
    ------
    RunDirError
        ``run_dir`` exists and is not empty, or is a file (nothing is overwritten).
    """
    check_new_run_dir(run_dir)
    make_folder(run_dir)
    atomic_write_text(run_dir / "config.toml", tomli_w.dumps(config_dict(recipe, spec, coach_source)))
    if spec is not None:
        atomic_write_text(run_dir / "coach.toml", dumps_spec(spec))
    kind = {"seed": recipe.seed, "env_id": recipe.env_id, "coach": spec.name if spec is not None else "none",
            "algo": recipe.algo}  # fmt: skip
    record = new_record(RUN_SCHEMA, argv if argv is not None else sys.argv, extra=kind)
    write_record(run_dir / "run.json", record)


def record_resume(
    run_dir: Path, argv: list[str] | None, from_env_steps: int, budget_env_steps: int, **extra: Any
) -> None:
    """Add a resume (now, the command, versions, git state, where it resumed) to ``run.json``.

    ``extra`` goes into the entry too (e.g. ``damaged_checkpoints``: those a resume fell back from).

    Raises
    ------
    RunDirError
        ``run.json`` is unreadable.
    """
    path = run_dir / "run.json"
    record = read_record(path, RUN_SCHEMA, RunDirError)
    command = argv if argv is not None else sys.argv
    resumed = add_resume(
        record, command, from_env_steps=from_env_steps, budget_env_steps=budget_env_steps, **extra
    )
    write_record(path, resumed)


def evaluated_at(run_dir: Path, env_steps: int) -> bool:
    """Whether the run's last agent-alone evaluation was at ``env_steps``."""
    rows = read_csv_rows(run_dir / "evaluations.csv")
    return bool(rows) and int(rows[-1]["env_steps_so_far"]) == env_steps


def finished_summary(run_dir: Path, budget: int) -> dict[str, Any] | None:
    """``summary.json`` when it says the run completed ``budget`` env steps, else None.

    The one reading of "is this run finished?" (the sweep skips such runs, ``resume`` returns them).

    Raises
    ------
    RunDirError
        ``summary.json`` exists but is damaged (not JSON, not an object, a count that is not a number).
    """
    path = run_dir / "summary.json"
    if not path.exists():
        return None
    summary = load_json(path, "run summary", RunDirError)
    if not isinstance(summary, dict):
        raise RunDirError(f"{path}: the run summary is damaged (not a JSON object)")
    try:
        done = bool(summary.get("completed")) and int(summary.get("env_steps", 0)) >= budget
    except (TypeError, ValueError) as exc:
        raise RunDirError(f"{path}: the run summary is damaged ({exc})") from None
    return summary if done else None
