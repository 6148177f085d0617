"""Runs shared between experiments: a run with the same settings is trained once.

An experiment that adds conditions to an earlier one (``none`` and ``rescue-terminal`` again,
beside a new coupling) names the earlier folder with ``pidlab experiment --reuse DIR``. Each of
its runs that has not started yet and that DIR holds finished, for the same env, condition and
seed whose own ``config.toml`` records the same settings (their digest,
:func:`pidlab.rl.rundir.settings_digest`: the recipe with the run's algorithm, the budget and the
coach, not the folder), is copied instead of trained. Training is
deterministic for a seed and its settings, so the copy is the run that training would have
made; each copy keeps its own ``run.json`` (the command and git SHA that trained it) and gets a
``reused.json`` saying where it came from. The experiment's ``experiment.json`` lists the copies
under ``reused`` and its report counts them.

A copy is atomic: the run is copied beside its place and renamed into it, so a sweep killed
mid-copy leaves no half run (the next sweep removes the leftover and copies again).
"""

from __future__ import annotations

import shutil
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pidlab.errors import ExperimentError, PidlabError, RunDirError
from pidlab.files import write_json
from pidlab.provenance import LOCK_NAME, now, read_record, write_record
from pidlab.rl.rundir import finished_summary, latest_checkpoint, stored_settings_digest

REUSED_NAME = "reused.json"
"""The file in a copied run that says where it came from."""

_PARTIAL = ".reuse-partial"
"""Suffix of a copy in progress (beside the run's place, removed when a copy is retried)."""


@dataclass(frozen=True)
class Reuse:
    """One run to copy instead of training it.

    Attributes
    ----------
    key : str
        ``ENV/CONDITION/SEED``, as in an experiment's identity.
    source : Path
        The finished run directory in the earlier experiment.
    target : Path
        The run directory in this experiment.
    origin : dict
        Where it came from: the earlier experiment's folder, command and git SHA, the digest.
    """

    key: str
    source: Path
    target: Path
    origin: dict[str, Any]


@dataclass(frozen=True)
class Source:
    """An earlier experiment whose finished runs may be copied."""

    folder: Path
    runs: dict[str, str]
    command: tuple[str, ...]
    git: str


def read_source(folder: str | Path, out: Path) -> Source:
    """Read an earlier experiment named by ``--reuse``.

    Raises
    ------
    ExperimentError
        One line: the folder is missing, is this experiment's own, or holds no readable experiment.
    """
    path = Path(folder)
    shown = f"--reuse {folder}"
    expected = "expected an earlier pidlab experiment's folder"
    if path.resolve() == out.resolve():
        raise ExperimentError(f"{shown}: that is this experiment's own folder ({expected})")
    if not path.is_dir():
        raise ExperimentError(f"{shown}: no such folder ({expected})")
    meta = path / "experiment.json"
    if not meta.is_file():
        raise ExperimentError(f"{shown}: holds no experiment.json ({expected})")
    from pidlab.experiment.sweep import EXPERIMENT_SCHEMA

    record = read_record(meta, EXPERIMENT_SCHEMA, ExperimentError)
    identity = record.identity
    runs = identity.get("runs") if isinstance(identity, dict) else None
    if record.schema != EXPERIMENT_SCHEMA or not isinstance(runs, dict):
        raise ExperimentError(f"{shown}: {meta} is not an experiment record (no identity with its runs)")
    sha = str((record.git or {}).get("sha") or "?")
    return Source(path.resolve(), {str(k): str(v) for k, v in runs.items()}, record.command, sha)


def find_reuses(tasks: Iterable[Any], folders: Sequence[str | Path], out: Path) -> tuple[Reuse, ...]:
    """The runs of ``tasks`` to copy from the earlier experiments in ``folders`` (the first that has one).

    A task is copied when its run has not started here (no checkpoint, no finished summary) and
    an earlier experiment lists the same key with the same digest and holds that run finished,
    with logs the report can read. Nothing is written.

    Raises
    ------
    ExperimentError
        One line: a folder is not an earlier experiment, or a run it offers is damaged.
    """
    sources = [read_source(f, out) for f in folders]
    found = []
    for task in tasks:
        key = f"{task.env_id}/{task.condition}/{task.seed}"
        target = Path(task.run_dir)
        if not sources or _started(target, int(task.recipe["steps"])):
            continue
        for src in sources:
            run = src.folder / "runs" / task.env_id / task.condition / f"seed-{task.seed}"
            same = key in src.runs and stored_settings_digest(run) == task.digest  # what the run itself did
            if same and _offered(run, int(task.recipe["steps"])):
                origin = {"experiment": str(src.folder), "command": list(src.command), "git": src.git,
                          "digest": task.digest}  # fmt: skip
                found.append(Reuse(key, run, target, origin))
                break
    return tuple(found)


def _started(run_dir: Path, budget: int) -> bool:
    """Whether this experiment already has something of the run: a checkpoint or a finished summary."""
    if not run_dir.is_dir():
        return False
    try:
        return latest_checkpoint(run_dir) is not None or finished_summary(run_dir, budget) is not None
    except (PidlabError, OSError):
        return True  # damaged here: the sweep's resume says what is wrong


def _offered(run: Path, budget: int) -> bool:
    """The earlier run is finished for ``budget`` with readable logs; damage is refused in one line."""
    from pidlab.experiment.analysis import LOG_DAMAGE, read_logs

    if not run.is_dir() or run.is_symlink():
        return False
    try:
        summary = finished_summary(run, budget)
        if summary is None:
            return False
        read_logs(run, summary)
    except (RunDirError, *LOG_DAMAGE) as exc:
        raise ExperimentError(
            f"--reuse: {run}: the finished run's logs are damaged ({type(exc).__name__}: {exc}); nothing was "
            "changed. Repair that experiment (repeat its command), or leave this run out of --reuse"
        ) from None
    if any(p.is_symlink() for p in run.rglob("*")):
        raise ExperimentError(f"--reuse: {run}: holds a symbolic link (expected a run folder of plain files)")
    return True


def copy_run(r: Reuse) -> None:
    """Copy one finished run into its place, atomically, with ``reused.json`` saying where it came from.

    The place holds nothing of the run's training (:func:`find_reuses` checked it); whatever it
    holds (a run killed before its first checkpoint) is replaced.
    """
    partial = r.target.with_name(f".{r.target.name}{_PARTIAL}")
    if partial.exists():
        shutil.rmtree(partial)  # a copy killed halfway
    r.target.parent.mkdir(parents=True, exist_ok=True)
    shutil.copytree(r.source, partial, ignore=shutil.ignore_patterns(LOCK_NAME))
    write_json(partial / REUSED_NAME, {"from": str(r.source), "copied": now(), **r.origin})
    if r.target.exists():
        old = r.target.with_name(f".{r.target.name}.reuse-old")
        shutil.rmtree(old, ignore_errors=True)
        r.target.rename(old)
        partial.rename(r.target)
        shutil.rmtree(old, ignore_errors=True)
    else:
        partial.rename(r.target)


def record_reuses(meta: Path, reuses: Sequence[Reuse]) -> None:
    """Add ``reuses`` to the ``reused`` field of the experiment's record (written atomically)."""
    if not reuses:
        return
    from pidlab.experiment.sweep import EXPERIMENT_SCHEMA

    record = read_record(meta, EXPERIMENT_SCHEMA, ExperimentError)
    listed = dict(record.extra.get("reused") or {})
    listed.update({r.key: r.origin for r in reuses})
    write_record(meta, record.with_extra(reused=dict(sorted(listed.items()))))


def reuse_sentence(record: dict[str, Any] | Any) -> str:
    """The report's sentence on copied runs (with a leading space), or "" when none was copied."""
    reused = record.get("reused") if isinstance(record, dict) else None
    if not isinstance(reused, dict) or not reused:
        return ""
    by_source: dict[str, int] = {}
    for origin in reused.values():
        o = origin if isinstance(origin, dict) else {}
        name = f"{Path(str(o.get('experiment', '?'))).name} (git {str(o.get('git', '?'))[:12]})"
        by_source[name] = by_source.get(name, 0) + 1
    where = ", ".join(f"{n} from {s}" for s, n in by_source.items())
    return (
        f" Copied, not trained, because an earlier experiment had them with the same settings: "
        f"{len(reused)} runs ({where}); each keeps the run.json of its training and says where it came "
        f"from in {REUSED_NAME}."
    )
