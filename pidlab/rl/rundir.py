"""Run directories: what a training run writes, how it is read back, and how it is cut back on resume.

A run directory holds ``config.toml`` (the resolved recipe and the coach's name, source and
digest), ``coach.toml`` (the spec), ``run.json`` (seed, command, versions, git SHA, resumes: a
:class:`pidlab.provenance.Record`), ``episodes.csv``, ``evaluations.csv``, ``tb/``,
``checkpoints/<env steps>/`` and, once the budget is spent, ``final_model.zip`` and
``summary.json``. See :mod:`pidlab.rl.train`.
"""

from __future__ import annotations

import csv
import io
import os
import sys
from pathlib import Path
from typing import Any

import tomli_w

from pidlab.controller.spec import CoachSpec, dumps_spec, loads_spec
from pidlab.errors import RunDirError
from pidlab.files import atomic_write_text, read_toml
from pidlab.provenance import (
    Refusals,
    add_resume,
    check_folder,
    digest,
    new_record,
    read_record,
    write_record,
)
from pidlab.rl.recipe import Recipe, parse_recipe, recipe_to_dict

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
)
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
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def truncate_csv(path: Path, columns: tuple[str, ...], keep: int) -> None:
    """Keep the header and the first ``keep`` complete rows of a run's CSV file (atomically).

    Raises
    ------
    RunDirError
        The file holds fewer complete rows than ``keep``.
    """
    rows: list[list[str]] = []
    if path.exists():
        with open(path, newline="", encoding="utf-8") as fh:
            reader = csv.reader(fh)
            next(reader, None)
            for row in reader:
                if len(rows) >= keep:
                    break
                if len(row) == len(columns):
                    rows.append(row)
    if len(rows) < keep:
        raise RunDirError(f"{path}: holds {len(rows)} complete rows, the checkpoint recorded {keep}")
    atomic_write_text(path, _csv_text(columns, rows))


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


def latest_checkpoint(run_dir: Path) -> Path | None:
    """The newest complete checkpoint folder (one with ``state.json``), or None."""
    folder = run_dir / "checkpoints"
    if not folder.is_dir():
        return None
    done = sorted(p for p in folder.iterdir() if p.is_dir() and (p / "state.json").exists())
    return done[-1] if done else None


def spec_digest(spec: CoachSpec) -> str:
    """SHA-256 of the spec's canonical text (what a run was coached by)."""
    return digest(dumps_spec(spec))


def config_dict(recipe: Recipe, spec: CoachSpec | None, coach_source: str | None) -> dict[str, Any]:
    """The tables of ``config.toml``: the resolved recipe and which coach (name, source, SHA-256)."""
    coach: dict[str, Any] = {"name": "none"}
    if spec is not None:
        coach = {"name": spec.name, "source": coach_source or "", "sha256": spec_digest(spec)}
    return {
        "schema": "pidlab.run-config/1",
        "env_id": recipe.env_id,
        "recipe_source": recipe.path or "",
        "coach": coach,
        "recipe": recipe_to_dict(recipe),
    }


def load_run_config(run_dir: str | Path) -> tuple[Recipe, CoachSpec | None, dict[str, Any]]:
    """The resolved recipe and coach spec a run directory was started with.

    Raises
    ------
    RunDirError
        Not a run directory.
    """
    run_dir = Path(run_dir)
    path = run_dir / "config.toml"
    if not path.exists():
        raise RunDirError(f"{run_dir}: not a pidlab run directory (no config.toml)")
    config = read_toml(path, "run config", RunDirError)
    recipe = parse_recipe(config["recipe"], f"{path}:recipe")
    spec_path = run_dir / "coach.toml"
    spec = loads_spec(spec_path.read_text(encoding="utf-8"), str(spec_path)) if spec_path.exists() else None
    return recipe, spec, config


def default_run_dir(recipe: Recipe, spec: CoachSpec | None, root: str | Path = "runs") -> Path:
    """``runs/<env>/<coach>-<algo>-seed<seed>``."""
    coach = spec.name if spec is not None else "none"
    return Path(root) / recipe.env_id / f"{coach}-{recipe.algo}-seed{recipe.seed}"


RUN_SCHEMA = "pidlab.run/1"


def _refusals(run_dir: Path) -> Refusals:
    taken = f"{run_dir} exists and is not empty; resume it with --resume {run_dir}, or choose --run-dir"
    return Refusals(
        not_a_folder=f"{run_dir} exists and is not a folder; choose another --run-dir",
        not_a_record=taken,
        not_ours=taken,
        another=lambda _record: taken,
    )


def prepare_run_dir(
    run_dir: Path, recipe: Recipe, spec: CoachSpec | None, coach_source: str | None, argv: list[str] | None
) -> None:
    """Create a new run directory with ``config.toml``, ``coach.toml`` and ``run.json``.

    Raises
    ------
    RunDirError
        ``run_dir`` exists and is not empty, or is a file (nothing is overwritten).
    """
    refusals = _refusals(run_dir)
    if check_folder(run_dir, "run.json", RUN_SCHEMA, None, refusals, RunDirError) is not None:
        raise RunDirError(refusals.not_ours)  # a run is resumed with resume(), never started again
    run_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(run_dir / "config.toml", tomli_w.dumps(config_dict(recipe, spec, coach_source)))
    if spec is not None:
        atomic_write_text(run_dir / "coach.toml", dumps_spec(spec))
    kind = {"seed": recipe.seed, "env_id": recipe.env_id, "coach": spec.name if spec is not None else "none",
            "algo": recipe.algo}  # fmt: skip
    record = new_record(RUN_SCHEMA, argv if argv is not None else sys.argv, extra=kind)
    write_record(run_dir / "run.json", record)


def record_resume(run_dir: Path, argv: list[str] | None, from_env_steps: int, budget_env_steps: int) -> None:
    """Add a resume (now, the command, versions, git state, where it resumed) to ``run.json``.

    Raises
    ------
    RunDirError
        ``run.json`` is unreadable.
    """
    path = run_dir / "run.json"
    record = read_record(path, RUN_SCHEMA, RunDirError)
    command = argv if argv is not None else sys.argv
    resumed = add_resume(record, command, from_env_steps=from_env_steps, budget_env_steps=budget_env_steps)
    write_record(path, resumed)


def evaluated_at(run_dir: Path, env_steps: int) -> bool:
    """Whether the run's last agent-alone evaluation was at ``env_steps``."""
    rows = read_csv_rows(run_dir / "evaluations.csv")
    return bool(rows) and int(rows[-1]["env_steps_so_far"]) == env_steps
