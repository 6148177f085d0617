"""Multi-seed coaching experiments: plan a sweep, run it on a process pool or Ray, resume it.

An experiment is every (env, condition, seed) combination, each trained by
:func:`pidlab.rl.train.train` into its own run directory::

    OUT/
      experiment.json                   what was asked (envs, conditions, seeds), the command,
                                        versions, git SHA, and the digest of every run's settings
      runs/ENV/CONDITION/seed-S/        one run directory each (see pidlab.rl.train)
      report.md, report.html, figures/  written by pidlab.report.experiment

A sweep that is killed and started again with the same command skips finished runs, resumes
unfinished ones from their last checkpoint, and starts the rest. A folder that holds another
experiment (other envs, conditions, seeds or settings) is refused, and nothing in it is touched.
A sweep holds the lock of OUT (:func:`pidlab.provenance.hold_lock`) while it runs, and each run
the lock of its run directory: a second sweep in OUT, or a ``pidlab train --resume`` of one of
its runs, is refused.

Pool workers stop with their parent (:func:`pidlab.orphans.stop_with_parent`): when the sweep's
process is killed, a busy worker stops its run with a checkpoint and exits within seconds, and no
worker starts another run.

Backends: ``process`` (a local process pool, one run per core) and ``ray`` (Ray tasks on a local
instance or, with ``address``, on a cluster whose nodes all have pidlab installed and see OUT).
"""

from __future__ import annotations

import importlib.util
import json
import os
import shlex
import shutil
import signal
import socket
import sys
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from pidlab.checks import (
    MAX_SEEDS,
    SEED_MAX,
    check_ascii_digits,
    check_name,
    clip,
    is_file,
    path_under,
    shown,
    split_list,
)
from pidlab.checks import seed as check_seed
from pidlab.controller.spec import CoachSpec, parse_spec, spec_to_dict
from pidlab.data import portable_name
from pidlab.errors import ExperimentError, PidlabError, RunDirError
from pidlab.experiment.conditions import (
    Condition,
    check_plan_arguments,
    check_sweep_arguments,
    load_conditions,
    resolve,
    select,
)
from pidlab.experiment.progress import steps_done
from pidlab.experiment.reuse import Reuse, copy_run, find_reuses, record_reuses
from pidlab.files import read_file
from pidlab.orphans import orphaned, stop_with_parent
from pidlab.parallel import resolve_workers
from pidlab.provenance import (
    LOCK_NAME,
    Record,
    Refusals,
    add_resume,
    check_folder,
    hold_lock,
    new_record,
    read_record,
    write_record,
)
from pidlab.rl.recipe import (
    Recipe,
    default_recipe_path,
    load_recipe,
    parse_recipe,
    recipe_envs,
    recipe_to_dict,
    with_overrides,
)
from pidlab.rl.rundir import finished_summary, latest_checkpoint, settings_digest, stored_settings_digest

EXPERIMENT_SCHEMA = "pidlab.experiment/1"
DIGESTS = 2
"""How a run's settings digest is made: :func:`pidlab.rl.rundir.settings_digest` (2: of the run's own
algorithm table only). Records without ``digests`` hold digests of every algorithm table (1); a
sweep reads such a folder by its runs' own ``config.toml`` (:func:`_recorded_identity`)."""
BACKENDS = ("process", "ray")


@dataclass(frozen=True)
class RunTask:
    """One run of a sweep, in plain data (it crosses process and machine boundaries)."""

    env_id: str
    condition: str
    seed: int
    run_dir: str
    recipe: dict[str, Any]
    spec: dict[str, Any] | None
    coach_source: str | None
    digest: str


@dataclass(frozen=True)
class RunOutcome:
    """What became of a :class:`RunTask`: ``done``, ``skipped``, ``reused``, ``stopped`` or ``failed``.

    ``skipped``: finished before; ``reused``: copied from an earlier experiment.
    """

    env_id: str
    condition: str
    seed: int
    status: str
    wall_s: float = 0.0
    error: str = ""


@dataclass(frozen=True)
class Plan:
    """A planned experiment: where, what, and every run."""

    out: Path
    envs: tuple[str, ...]
    conditions: tuple[str, ...]
    seeds: tuple[int, ...]
    tasks: tuple[RunTask, ...]
    recipes: dict[str, Recipe] = field(compare=False)
    descriptions: dict[str, str] = field(compare=False)

    def identity(self) -> dict[str, Any]:
        """What makes two experiments the same: envs, conditions, seeds and every run's settings.

        ``digests`` names how the runs' digests are made (:data:`DIGESTS`).
        """
        runs = {f"{t.env_id}/{t.condition}/{t.seed}": t.digest for t in self.tasks}
        return {"envs": list(self.envs), "conditions": list(self.conditions), "seeds": list(self.seeds),
                "runs": runs, "digests": DIGESTS}  # fmt: skip


def parse_seeds(seeds: str, default_count: int | None = None) -> tuple[int, ...]:
    """Seeds from ``N`` (0..N-1), ``A-B`` (inclusive) or ``A,B,C``.

    At most :data:`pidlab.checks.MAX_SEEDS` seeds, each in ``[0, 2**32 - 1]`` (what SB3 accepts),
    checked before any list is made.

    Raises
    ------
    ExperimentError
        Empty, negative, too large, too many, repeated or unreadable.
    """

    def bad(reason: str) -> ExperimentError:
        return ExperimentError(f"seeds={shown(seeds)}: {reason}", param="seeds")

    if not isinstance(seeds, str):
        raise bad("expected a count (10), a range (0-9) or a list (0,3,7)")
    check_ascii_digits(seeds, "seeds", ExperimentError, param="seeds")
    t = seeds.strip()
    values: list[int] = []
    try:
        if t.isdigit():
            low, high = 0, int(t) - 1
        elif "-" in t and "," not in t:
            low, high = (int(v) for v in t.split("-", 1))
        else:
            values = [int(v) for v in split_list(t, "seeds", ExperimentError, what="seeds")]
            low, high = min(values, default=0), max(values, default=-1)
    except ValueError:
        raise bad("expected a count (10), a range (0-9) or a list (0,3,7)") from None
    count = len(values) if values else high - low + 1
    if count < 1:
        raise bad("no seeds; expected at least one (e.g. 10)")
    if count > MAX_SEEDS:
        raise bad(f"{count} seeds; expected at most {MAX_SEEDS}")
    if low < 0 or high > SEED_MAX:
        raise bad(f"expected seeds in [0, {SEED_MAX}]")
    out = tuple(values) if values else tuple(range(low, high + 1))
    if len(set(out)) != len(out):
        raise bad("seeds must be distinct non-negative integers")
    return out


def _check_names(envs: Sequence[str], seeds: Sequence[int]) -> None:
    """Each env id a name of :data:`pidlab.checks.NAME_RULE`, each seed in ``[0, 2**32 - 1]``."""
    if not envs:
        raise ExperimentError("envs=[]: no env; name at least one, e.g. InvertedPendulum-v5", param="envs")
    if not seeds:
        raise ExperimentError("seeds=[]: no seeds; expected at least one (e.g. 10)", param="seeds")
    for env_id in envs:
        check_name(env_id, "envs", ExperimentError, param="envs")
    if len(set(envs)) != len(envs):
        raise ExperimentError(f"envs={', '.join(envs)}: an env is named twice", param="envs")
    if len(seeds) > MAX_SEEDS:
        raise ExperimentError(f"seeds: {len(seeds)} seeds; expected at most {MAX_SEEDS}", param="seeds")
    for s in seeds:
        check_seed(s, "seeds", ExperimentError, param="seeds")
    if len(set(seeds)) != len(seeds):
        raise ExperimentError("seeds: seeds must be distinct", param="seeds")


def _load_recipes(
    envs: Sequence[str], recipe_files: Sequence[str], algo: str | None, steps: int | None
) -> dict[str, Recipe]:
    """Each env's recipe (one of ``recipe_files``, else ``coach/ENV.toml``) with the overrides."""
    given: dict[str, Recipe] = {}
    for path in recipe_files:
        if not is_file(path):
            raise ExperimentError(f"recipe_files={clip(str(path))}: no such file", param="recipe_files")
        r = load_recipe(path)
        if r.env_id not in envs:
            raise ExperimentError(
                f"recipe_files={path}: the recipe is for {r.env_id}, which is not one of the envs asked for",
                param="recipe_files",
            )
        given[r.env_id] = r
    recipes: dict[str, Recipe] = {}
    for env_id in envs:
        if env_id not in given:
            default = default_recipe_path(env_id)
            if not default.is_file():
                raise ExperimentError(
                    f"envs={env_id}: unknown env (no recipe {default}); "
                    f"recipes exist for: {', '.join(recipe_envs())}",
                    param="envs",
                )
            given[env_id] = load_recipe(default)
        recipes[env_id] = with_overrides(given[env_id], algo=algo, steps=steps)
    return recipes


def _task(env_id: str, cond: Condition, base: Recipe, spec: CoachSpec | None, source: str | None, seed: int,
          root: Path) -> RunTask:  # fmt: skip
    recipe = replace(base, seed=int(seed))
    return RunTask(
        env_id=env_id,
        condition=cond.name,
        seed=int(seed),
        run_dir=str(path_under(root, "runs", env_id, cond.name, f"seed-{seed}", error=ExperimentError)),
        recipe=recipe_to_dict(recipe),
        spec=spec_to_dict(spec) if spec is not None else None,
        coach_source=source,
        digest=settings_digest(recipe, spec),  # what the run does, not where its files came from
    )


def _check_fits(env_id: str, condition: str, recipe: Recipe, spec: CoachSpec | None) -> None:
    """The condition's coach has the takeover region its coaching tests, before any run starts.

    Raises
    ------
    ExperimentError
        For example the predictive trigger with a spec that has no rescue region.
    """
    from pidlab.plant.card import find_card
    from pidlab.rl.coaching import takeover_region

    c = recipe.coaching
    card = find_card(env_id)
    if spec is None or card is None or not (c.trigger is None or isinstance(c.trigger, str)):
        return  # no coach, no card to check against, or a growth trigger (it uses no region)
    try:
        takeover_region(spec, card.observation_names, c.region, c.trigger == "predictive", c.width)
    except PidlabError as exc:
        raise ExperimentError(f"condition {condition!r} on {env_id}: {exc}") from None


def plan(
    envs: Sequence[str],
    condition_names: Sequence[str],
    seeds: Sequence[int],
    out: str | Path,
    *,
    conditions_file: str | Path | None = None,
    recipe_files: Sequence[str] = (),
    algo: str | None = None,
    steps: int | None = None,
) -> Plan:
    """Check every input and list the runs of an experiment (nothing is written).

    Parameters
    ----------
    envs : sequence of str
        Env ids; each needs a recipe (``coach/ENV.toml`` or one of ``recipe_files``).
    condition_names : sequence of str
        Names in the conditions file.
    seeds : sequence of int
    out : path
        The experiment folder.
    conditions_file : path, optional
        Default ``coach/conditions.toml``.
    recipe_files : sequence of str
        Recipes to use instead of ``coach/ENV.toml`` (their ``env_id`` says for which env).
    algo, steps : optional
        Overrides of every recipe's algorithm and budget (env steps).

    Raises
    ------
    ExperimentError, RecipeError, ConditionError, SpecError
        One line naming what is wrong.
    """
    check_plan_arguments(envs, condition_names, seeds, out, conditions_file, recipe_files, algo, steps)
    _check_names(envs, seeds)
    conditions: dict[str, Condition] = load_conditions(conditions_file)
    chosen = select(conditions, list(condition_names), str(conditions_file or "coach/conditions.toml"))
    recipes = _load_recipes(envs, recipe_files, algo, steps)
    root = Path(out).resolve()
    tasks = []
    for env_id in envs:
        for cond in chosen:
            base, spec, source = resolve(cond, recipes[env_id])
            _check_fits(env_id, cond.name, base, spec)
            tasks += [_task(env_id, cond, base, spec, source, seed, root) for seed in seeds]
    return Plan(
        out=root,
        envs=tuple(envs),
        conditions=tuple(c.name for c in chosen),
        seeds=tuple(int(s) for s in seeds),
        tasks=tuple(tasks),
        recipes=recipes,
        descriptions={c.name: c.description for c in chosen},
    )


def _describe_difference(old: Record, new: dict[str, Any]) -> str:
    """What differs between the folder's experiment and the one asked for, in a few words."""
    recorded = old.identity or {}
    for key in ("envs", "conditions", "seeds"):
        if recorded.get(key) != new.get(key):
            return f"its {key} {recorded.get(key)} (asked: {new.get(key)})"
    runs = recorded.get("runs") or {}
    changed = [name for name, digest in new["runs"].items() if runs.get(name) != digest]
    where = f"{len(changed)} of its {len(new['runs'])} runs, e.g. {changed[0]}" if changed else "its runs"
    return (
        f"other settings for {where}: budget, algorithm, recipe, coach spec or condition; "
        f"it was made by: {shlex.join(old.command)}"
    )


def _recorded_identity(p: Plan) -> dict[str, Any] | None:
    """The identity a folder's older record holds, when that record is of this very experiment.

    A record without ``digests`` (made before :data:`DIGESTS` 2) holds digests that cover every
    algorithm table of the recipes. It is this experiment when its envs, conditions, seeds and run
    keys are the plan's and every run that has started (it has a ``config.toml``) records settings
    whose digest is the plan's for it: what each run did is read from the run itself. Runs that
    have not started will run with the plan's settings. None otherwise (and for a current record).
    """
    try:
        old = read_record(p.out / "experiment.json", EXPERIMENT_SCHEMA, ExperimentError)
    except (ExperimentError, OSError):
        return None
    recorded = old.identity if isinstance(old.identity, dict) else None
    if recorded is None or "digests" in recorded:
        return None
    new = p.identity()
    if any(recorded.get(k) != new[k] for k in ("envs", "conditions", "seeds")):
        return None
    if not isinstance(recorded.get("runs"), dict) or set(recorded["runs"]) != set(new["runs"]):
        return None
    for t in p.tasks:
        stored = stored_settings_digest(t.run_dir)
        if (Path(t.run_dir) / "config.toml").exists() and stored != t.digest:
            return None
    return recorded


def check_out_folder(p: Plan) -> Record | None:
    """The folder's ``experiment.json`` when it holds this experiment, None when new or empty.

    Nothing is written or removed.

    Raises
    ------
    ExperimentError
        The folder is a file, or holds another experiment, or files that are not an experiment's.
    """
    out, identity = p.out, p.identity()
    identity = _recorded_identity(p) or identity

    def another(old: Record) -> str:
        return (
            f"out={out}: holds another experiment ({_describe_difference(old, identity)}); "
            "nothing was changed. Choose another folder, or repeat that experiment's own command to resume it"
        )

    refusals = Refusals(
        not_a_folder=f"out={out}: exists and is not a folder",
        not_a_record=f"out={out}: experiment.json is not an experiment record; nothing was changed. "
        "Choose a new or empty folder",
        not_ours=f"out={out}: the folder is not empty and holds no experiment.json; nothing was changed. "
        "Choose a new or empty folder",
        another=another,
    )
    return check_folder(out, "experiment.json", EXPERIMENT_SCHEMA, identity, refusals, ExperimentError, "out")


def write_experiment_record(p: Plan, argv: Sequence[str], backend: str) -> Record:
    """Create (or on resume, extend) ``experiment.json``.

    Raises
    ------
    ExperimentError
        ``experiment.json`` is unreadable.
    """
    meta = p.out / "experiment.json"
    if meta.exists():
        record = add_resume(read_record(meta, EXPERIMENT_SCHEMA, ExperimentError), argv, backend=backend)
        record = replace(record, identity=p.identity())  # an older record's digests, made current
    else:
        recipes = {env: portable_name(r.path or "") for env, r in p.recipes.items()}  # not the writer's path
        kind = {"backend": backend, "descriptions": p.descriptions, "recipes": recipes,
                "python": sys.version.split()[0]}  # fmt: skip
        record = new_record(EXPERIMENT_SCHEMA, argv, identity=p.identity(), extra=kind)
    p.out.mkdir(parents=True, exist_ok=True)
    write_record(meta, record)
    return record


def dispatch_order(tasks: Sequence[RunTask]) -> list[RunTask]:
    """The order runs start in: seed by seed, every env and condition of a seed before the next seed.

    A sweep stopped part-way (a session that ends, see benchmarks/evidence.sh) then holds every
    condition at the same seeds, so its finished runs compare like with like. The plan's order
    (env, condition, seed), which the record and the report use, is unchanged.
    """
    rank: dict[int, int] = {}
    for t in tasks:
        rank.setdefault(t.seed, len(rank))
    return sorted(tasks, key=lambda t: rank[t.seed])  # stable: env and condition order kept


def finished(run_dir: Path, budget: int) -> bool:
    """A run whose ``summary.json`` says it completed its budget (a damaged one says nothing)."""
    try:
        return finished_summary(run_dir, budget) is not None
    except RunDirError:
        return False  # its resume says what is wrong, and writes it again


def check_finished_logs(run_dirs: Iterable[Path]) -> None:
    """The logs of every finished run in ``run_dirs`` read as the report reads them; nothing is written.

    A sweep skips a finished run and its report reads the run's logs: logs damaged since (an
    ``episodes.csv`` cut short) are refused before the sweep writes anything, with the command
    that repairs the experiment. A run without a readable ``summary.json`` is not finished: the
    sweep resumes it, and the resume checks its logs.

    Raises
    ------
    ExperimentError
        One line naming the run, what is damaged, and what to do.
    """
    from pidlab.experiment.analysis import LOG_DAMAGE, logs_damaged, read_logs

    for run_dir in run_dirs:
        try:
            summary = json.loads(read_file(run_dir / "summary.json").decode("utf-8"))
        except (OSError, ValueError, RecursionError):
            continue
        if not isinstance(summary, dict) or not summary.get("completed"):
            continue
        try:
            read_logs(run_dir, summary)
        except LOG_DAMAGE as exc:
            raise logs_damaged(run_dir, exc, "run this command again") from None


STOP_FILE = ".stopping"
STOP_TIMEOUT_S = 300.0  # how long an interrupted sweep waits for its runs to checkpoint
POLL_S = 10.0  # how often a sweep reads its running runs' progress from their logs


RUN_LOCK_WAIT_S = 30.0
"""How long a run waits for its lock (an orphan of a killed sweep may still be checkpointing it)."""


def execute(task: RunTask) -> RunOutcome:
    """Run (or resume, or skip) one task; every failure becomes an outcome, never an exception.

    In a pool worker whose sweep is gone, it starts nothing and ends the worker.
    """
    if orphaned(_PARENT[0]):
        os._exit(0)
    _BUSY[0] = True
    try:
        return _execute(task)
    finally:
        _BUSY[0] = False
        if orphaned(_PARENT[0]):  # nobody to report to: the run has stopped with a checkpoint
            os._exit(0)


def _clear(run_dir: Path) -> None:
    """Empty a run directory but its lock (a run killed before its first checkpoint starts again)."""
    for entry in run_dir.iterdir():
        if entry.name == LOCK_NAME:
            continue
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry)
        else:
            entry.unlink()


def _execute(task: RunTask) -> RunOutcome:
    from pidlab.rl.train import resume, train

    started = time.perf_counter()
    run_dir = Path(task.run_dir)
    out = run_dir.parents[3]
    key = (task.env_id, task.condition, task.seed)
    if (out / STOP_FILE).exists():
        return RunOutcome(*key, status="stopped")
    budget = int(task.recipe["steps"])
    try:
        with hold_lock(run_dir, RunDirError, wait_s=RUN_LOCK_WAIT_S):
            if finished(run_dir, budget):
                return RunOutcome(*key, status="skipped")
            if latest_checkpoint(run_dir) is None:
                _clear(run_dir)  # killed before its first checkpoint: nothing to keep
            argv = ["pidlab experiment", f"{task.env_id}/{task.condition}/seed-{task.seed}"]
            if (run_dir / "config.toml").exists():
                result = resume(run_dir, progress_bar=False, argv=argv)
            else:
                recipe = parse_recipe(task.recipe, f"{task.env_id}/{task.condition}")
                spec = parse_spec(task.spec) if task.spec is not None else None
                result = train(recipe, spec, run_dir, coach_source=task.coach_source, progress_bar=False,
                               argv=argv)  # fmt: skip
    except Exception as exc:  # a run that fails is reported, the sweep goes on
        return RunOutcome(*key, status="failed", wall_s=time.perf_counter() - started,
                          error=f"{type(exc).__name__}: {exc}")  # fmt: skip
    return RunOutcome(*key, status="done" if result.completed else "stopped",
                      wall_s=time.perf_counter() - started)  # fmt: skip


_BUSY = [False]  # a pool worker is inside execute()
_PARENT: list[int | None] = [None]  # in a pool worker: the sweep's pid


def _term_in_worker(signum: int, frame: Any) -> None:
    """SIGTERM in a pool worker: interrupt the task; when idle, exit if the sweep is gone.

    A task outside its training loop (which stops politely by itself) ends as interrupted. An idle
    worker of a live sweep has nothing to save and waits for the pool's own shutdown: raising
    there would print a worker traceback and break the pool under a run that is still
    checkpointing. An idle worker whose sweep was killed exits at once.
    """
    if _BUSY[0]:
        raise KeyboardInterrupt
    if orphaned(_PARENT[0]):
        os._exit(0)


def _worker_init(parent: int) -> None:
    """Pool worker: leave terminal Ctrl-C to the parent, and stop when the parent (pid ``parent``) dies."""
    os.setsid()
    _PARENT[0] = parent
    signal.signal(signal.SIGTERM, _term_in_worker)
    stop_with_parent(parent, lambda: os.kill(os.getpid(), signal.SIGTERM))


Progress = Callable[[RunOutcome], None]


def _run_process_pool(tasks: Sequence[RunTask], workers: int, report: Progress, poll: Callable[[], None],
                      out: Path) -> None:  # fmt: skip
    import multiprocessing as mp
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    from concurrent.futures.process import BrokenProcessPool

    ctx = mp.get_context("spawn")
    pool = ProcessPoolExecutor(
        max_workers=workers, mp_context=ctx, initializer=_worker_init, initargs=(os.getpid(),)
    )
    futures = {pool.submit(execute, t) for t in tasks}
    try:
        while futures:
            done, futures = wait(futures, timeout=POLL_S, return_when=FIRST_COMPLETED)
            for f in done:
                report(f.result())
            poll()
    except (KeyboardInterrupt, BrokenProcessPool) as exc:  # interrupted, or a worker died
        _stop_runs(pool, futures, out, signal_them=isinstance(exc, KeyboardInterrupt))
        raise
    pool.shutdown(wait=True)


def _stop_runs(pool: Any, futures: set[Any], out: Path, signal_them: bool) -> None:
    """The sweep stops: queued runs return at once, running ones stop at their next step with a checkpoint.

    ``signal_them``: send each worker the SIGTERM that asks its run to stop. A pool broken by a
    worker that died has sent it itself (Python's executor terminates the rest); a second one would
    stop a run at once, without its checkpoint, so then the workers are only waited for. Either
    way, after :data:`STOP_TIMEOUT_S` the workers still alive (idle, or stuck) are ended.
    """
    from concurrent.futures import wait

    (out / STOP_FILE).touch()  # queued runs return at once
    procs = list((getattr(pool, "_processes", None) or {}).values())
    deadline = time.monotonic() + STOP_TIMEOUT_S
    if signal_them:
        for proc in procs:  # running runs stop at their next step with a checkpoint
            try:
                os.kill(proc.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
        wait([f for f in futures if not f.cancel()], timeout=STOP_TIMEOUT_S)
    else:
        for proc in procs:
            proc.join(max(0.0, deadline - time.monotonic()))
    for proc in procs:  # idle now (or stuck): end them rather than wait on the pool
        if proc.is_alive():
            proc.terminate()
    pool.shutdown(wait=False, cancel_futures=True)


def _join_ray(ray: Any, address: str) -> None:
    """Join the running cluster at ``address``.

    Raises
    ------
    ExperimentError
        No cluster answers there, or it refuses this driver (token authentication).
    """
    host, _, port = address.rpartition(":")
    if address != "auto" and "://" not in address:  # Ray waits minutes for a missing cluster: ask first
        try:
            socket.create_connection((host.strip("[]"), int(port)), timeout=5).close()
        except (OSError, ValueError) as exc:
            raise ExperimentError(
                f"--address {address}: no Ray cluster answers there ({exc}); expected HOST:PORT of a "
                "running cluster's head node (`ray start --head` prints it), or auto"
            ) from None
    try:
        ray.init(address=address, include_dashboard=False, log_to_driver=False)
    except (ConnectionError, ray.exceptions.AuthenticationError) as exc:
        why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ExperimentError(
            f"--address {address}: cannot join the Ray cluster ({why}); expected a running cluster "
            "(`ray start --head` on its head node); one with token authentication also needs "
            "RAY_AUTH_MODE=token and its token (~/.ray/auth_token or RAY_AUTH_TOKEN) here"
        ) from None


def _run_ray(tasks: Sequence[RunTask], report: Progress, poll: Callable[[], None], out: Path) -> None:
    """The tasks as Ray tasks, on the instance :func:`_ray_ready` started or joined."""
    import ray

    remote = ray.remote(num_cpus=1, max_retries=0)(execute)
    task_of = {remote.remote(t): t for t in tasks}
    pending = list(task_of)
    try:
        while pending:
            done, pending = ray.wait(pending, num_returns=1, timeout=POLL_S)
            for ref in done:
                try:
                    report(ray.get(ref))
                except ray.exceptions.RayError as exc:  # its worker died (killed, out of memory, node lost)
                    why = str(exc).strip().splitlines()[0] if str(exc).strip() else "no detail"
                    error = f"{type(exc).__name__}: {why}"
                    report(RunOutcome(*_key(task_of[ref]), status="failed", error=error))
            poll()
    except KeyboardInterrupt:
        (out / STOP_FILE).touch()
        for ref in pending:
            ray.cancel(ref)
        raise


@contextmanager
def _ray_ready(backend: str, workers: int, address: str | None) -> Iterator[None]:
    """Ray started (``workers`` CPUs) or joined (``address``) for the block; nothing for a process pool.

    The sweep enters it before it writes anything: a cluster that does not answer is a refusal
    that changes nothing. Ray is shut down at the end when the block started it.

    Raises
    ------
    ExperimentError
        No cluster answers at ``address``, or it refuses this driver.
    """
    if backend != "ray":
        yield
        return
    import ray

    started_here = not ray.is_initialized()
    if started_here:
        if address:
            _join_ray(ray, address)
        else:
            ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
    try:
        yield
    finally:
        if started_here:
            ray.shutdown()


STOPPED_BY = (
    "interrupted",
    "a run's worker process died (killed by a signal, or by the system out of memory)",
)
"""Why a sweep stopped early: SIGINT or SIGTERM, or a pool worker that died (the pool stops the others)."""


@dataclass(frozen=True)
class SweepResult:
    """Outcomes of a sweep, in task order.

    Attributes
    ----------
    outcomes : tuple of RunOutcome
    interrupted : bool
        The sweep stopped before its runs were done; the unfinished ones keep their last checkpoint.
    stopped_by : str or None
        Why (one of :data:`STOPPED_BY`); None when it was not stopped.
    """

    outcomes: tuple[RunOutcome, ...]
    interrupted: bool
    stopped_by: str | None = None

    def count(self, status: str) -> int:
        """How many runs ended with ``status``."""
        return sum(o.status == status for o in self.outcomes)


def check_sweep(
    p: Plan, *, backend: str = "process", workers: int | None = None, address: str | None = None,
    reuse: Sequence[str | Path] = (),
) -> tuple[Reuse, ...]:  # fmt: skip
    """Check what :func:`run_sweep` is asked (backend, workers, the folder); nothing is written.

    Returns
    -------
    tuple of Reuse
        The runs to copy from the earlier experiments ``reuse``
        (:func:`~pidlab.experiment.reuse.find_reuses`).

    Raises
    ------
    ExperimentError
        Unknown backend (or Ray not installed), a bad number of workers, an address without
        Ray, a folder that holds something else than this experiment, a finished run of it
        whose logs were damaged since (:func:`check_finished_logs`), or a ``reuse`` folder that
        is not an earlier experiment or offers a damaged run.
    """
    check_sweep_arguments(p, backend, workers, address, reuse=reuse)
    check_backend(backend, workers, address)
    check_out_folder(p)
    check_finished_logs(Path(t.run_dir) for t in p.tasks)
    return find_reuses(p.tasks, reuse, p.out)


def lock_experiment(p: Plan) -> AbstractContextManager[Path]:
    """Hold the lock of ``p``'s folder (a second command in it is refused); the folder is made.

    :func:`run_sweep` takes it; the command line takes it first, to hold it while it writes the
    report too (the lock is re-entrant within a process).

    Raises
    ------
    ExperimentError
        Another pidlab command works in the folder.
    """
    return hold_lock(p.out, ExperimentError, param="out")


def _term_as_interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


def check_backend(backend: str, workers: int | None, address: str | None) -> None:
    """Check where a sweep would run (backend, workers, Ray address); nothing is started.

    Raises
    ------
    ExperimentError
        An unknown backend, Ray not installed, an address without Ray, a worker count out of range.
    """
    if backend not in BACKENDS:
        raise ExperimentError(f"backend={backend!r}: expected one of {', '.join(BACKENDS)}", param="backend")
    if backend == "ray" and importlib.util.find_spec("ray") is None:
        raise ExperimentError(
            "backend=ray: Ray is not installed; install the extra: pip install 'pidlab[ray]'", param="backend"
        )
    if address and backend != "ray":
        raise ExperimentError(f"address={address!r}: only with the ray backend", param="address")
    if workers is not None:  # a sweep cannot use more workers than any other command (nor Ray more CPUs)
        resolve_workers(workers, ExperimentError)


def _copy(reuses: Sequence[Reuse], out: Path, tally: _Tally) -> None:
    """Copy the runs of earlier experiments (each atomically) and list them in ``experiment.json``."""
    for r in reuses:
        copy_run(r)
        env_id, condition, seed = r.key.rsplit("/", 2)
        tally(RunOutcome(env_id, condition, int(seed), "reused"))
    record_reuses(out / "experiment.json", reuses)


def _key(t: RunTask | RunOutcome) -> tuple[str, str, int]:
    return (t.env_id, t.condition, t.seed)


class _Tally:
    """The outcomes of a sweep as they arrive, and the progress bar that shows them.

    The bar counts env steps over every run (a run's budget once it is finished or copied, and
    while it trains what its log has reached, :func:`pidlab.experiment.progress.steps_done`), so
    that a sweep of hour-long runs shows its pace and the time it still needs. Without a bar each
    finished run prints a line instead.
    """

    def __init__(self, tasks: Sequence[RunTask], todo: Sequence[RunTask], progress_bar: bool,
                 copied: Iterable[Path] = ()) -> None:  # fmt: skip
        from tqdm.auto import tqdm

        later = {t.run_dir for t in todo}
        self.outcomes = {_key(t): RunOutcome(*_key(t), "skipped") for t in tasks
                         if t.run_dir not in later | {str(c) for c in copied}}  # fmt: skip
        self.budgets = {_key(t): int(t.recipe["steps"]) for t in tasks}
        self.dirs = {_key(t): Path(t.run_dir) for t in todo}
        self.steps = {k: steps_done(self.dirs[k], b) if k in self.dirs else b
                      for k, b in self.budgets.items()}  # fmt: skip
        self.shown = progress_bar
        self.total = sum(self.budgets.values())
        self.bar = tqdm(total=self.total, initial=sum(self.steps.values()), unit=" env step",
                        unit_scale=True, smoothing=0.0, desc="experiment", disable=not progress_bar,
                        dynamic_ncols=True)  # fmt: skip
        self.last = ""
        self._postfix()

    def _advance(self, key: tuple[str, str, int], steps: int) -> None:
        """Move a run's progress on to ``steps`` (never back: a resume rewinds to its checkpoint)."""
        new = max(self.steps[key], min(steps, self.budgets[key]))
        self.bar.update(new - self.steps[key])
        self.steps[key] = new

    def _ended(self) -> int:
        return sum(o.status in ("done", "skipped", "reused") for o in self.outcomes.values())

    def _postfix(self) -> None:
        self.bar.set_postfix_str(f"{self._ended()}/{len(self.budgets)} runs finished{self.last}")

    def poll(self) -> None:
        """Read the progress of the runs not yet reported from their logs."""
        for key, run_dir in self.dirs.items():
            if key not in self.outcomes:
                self._advance(key, steps_done(run_dir, self.budgets[key]))
        self._postfix()

    def __call__(self, o: RunOutcome) -> None:
        key = _key(o)
        self.outcomes[key] = o
        if o.status in ("done", "skipped", "reused"):
            self._advance(key, self.budgets[key])
        elif key in self.dirs:
            self._advance(key, steps_done(self.dirs[key], self.budgets[key]))
        name = f"{o.env_id}/{o.condition}/seed-{o.seed}"
        if o.status == "failed":
            self.bar.write(f"pidlab: run {name} failed: {o.error}", file=sys.stderr)
        elif not self.shown and o.status == "done":
            print(f"pidlab: run {name} done ({self._ended()} of {len(self.budgets)} runs finished; "
                  f"{sum(self.steps.values()):,} of {self.total:,} env steps)",
                  file=sys.stderr, flush=True)  # fmt: skip
        self.last = f"; last {o.env_id} {o.condition} seed {o.seed}: {o.status}"
        self._postfix()

    def ordered(self, tasks: Sequence[RunTask]) -> tuple[RunOutcome, ...]:
        """Every task's outcome, in task order (``stopped`` for a task that never reported)."""
        return tuple(self.outcomes.get(_key(t), RunOutcome(*_key(t), "stopped")) for t in tasks)


def _dispatch(todo: Sequence[RunTask], backend: str, workers: int, tally: _Tally, out: Path) -> str | None:
    """Run ``todo`` on the backend; why it stopped early (:data:`STOPPED_BY`), or None."""
    from concurrent.futures.process import BrokenProcessPool

    old = signal.signal(signal.SIGTERM, _term_as_interrupt)
    try:
        if todo:
            if backend == "process":
                _run_process_pool(todo, min(workers, len(todo)), tally, tally.poll, out)
            else:
                _run_ray(todo, tally, tally.poll, out)
    except KeyboardInterrupt:
        return STOPPED_BY[0]
    except BrokenProcessPool:
        return STOPPED_BY[1]
    finally:
        signal.signal(signal.SIGTERM, old)
        tally.bar.close()
    return None


def run_sweep(
    p: Plan,
    *,
    backend: str = "process",
    workers: int | None = None,
    address: str | None = None,
    argv: Sequence[str] = (),
    progress_bar: bool = True,
    reuse: Sequence[str | Path] = (),
) -> SweepResult:
    """Run every task of ``p`` that is not finished; resume the unfinished ones.

    A run not started here that an earlier experiment of ``reuse`` holds finished with the same
    settings is copied instead (:mod:`pidlab.experiment.reuse`).

    Parameters
    ----------
    p : Plan
    backend : {"process", "ray"}
    workers : int, optional
        Parallel runs (default: the machine's cores; for Ray with an address, the cluster decides).
    address : str, optional
        A Ray cluster to join (``ray`` backend only).
    argv : sequence of str
        The command, recorded in ``experiment.json``.
    progress_bar : bool
    reuse : sequence of path
        Earlier experiments' folders, searched in order.

    Returns
    -------
    SweepResult
        ``interrupted`` when SIGINT/SIGTERM stopped it (runs checkpointed; the same command resumes).

    Raises
    ------
    ExperimentError
        Unknown backend, a folder of another experiment, a finished run whose logs were damaged
        since, another command working in it, a Ray cluster that does not answer. Every input is
        checked before the first file is written: a refusal changes nothing.
    """
    check_sweep_arguments(p, backend, workers, address, argv, progress_bar, reuse)
    check_sweep(p, backend=backend, workers=workers, address=address, reuse=reuse)
    n = workers or os.cpu_count() or 1
    with lock_experiment(p):
        reuses = check_sweep(p, backend=backend, workers=workers, address=address, reuse=reuse)  # again
        copied = {r.target for r in reuses}
        todo = dispatch_order([t for t in p.tasks if Path(t.run_dir) not in copied
                               and not finished(Path(t.run_dir), int(t.recipe["steps"]))])  # fmt: skip
        with _ray_ready(backend if todo else "process", n, address):  # a refusal here writes nothing
            write_experiment_record(p, argv, backend)
            (p.out / STOP_FILE).unlink(missing_ok=True)
            tally = _Tally(p.tasks, todo, progress_bar, copied)
            _copy(reuses, p.out, tally)
            stopped_by = _dispatch(todo, backend, n, tally, p.out)
    return SweepResult(tally.ordered(p.tasks), stopped_by is not None, stopped_by)
