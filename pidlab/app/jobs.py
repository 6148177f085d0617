"""The tuner's slow parts, run in worker processes so the page never freezes.

A :class:`JobRunner` owns a small pool of spawned worker processes (lowered priority, so the
server process that answers slider moves keeps a core) and runs at most one job of each
*kind* at a time: submitting a new ``roa`` job abandons the running one (its progress
callback raises at the next report) and drops a queued one. The app polls
:meth:`JobRunner.poll` from its event loop and receives :class:`JobUpdate` records: progress
while a job runs, then its result or a one-line error.

The job functions (:func:`roa_preview`, :func:`rollout_preview`, :func:`autotune_job`,
:func:`bounds_job`) are plain functions of picklable arguments returning frozen dataclasses;
they can be called directly (tests do) with ``progress=None``.
"""

from __future__ import annotations

import functools
import itertools
import logging
import multiprocessing as mp
import os
import queue as queue_mod
import signal
import threading
import traceback
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from multiprocessing.managers import SyncManager
from typing import Any

import numpy as np

from pidlab.controller.spec import CoachSpec
from pidlab.errors import JobCancelled, PidlabError
from pidlab.orphans import signal_on_parent_death, watch_parent

log = logging.getLogger("pidlab.app")

Progress = Callable[[str, "float | None"], None]

ROA_PREVIEW_SAMPLES = 200
"""Simulated initial states in the live region-of-attraction preview (``pidlab bounds`` uses 1000)."""

ROA_PREVIEW_TRAJECTORIES = 40
ROLLOUT_EPISODES = 5
BOUNDS_SAMPLES = 1000


# --------------------------------------------------------------------------------------------
# Job functions (run in the workers)


@functools.lru_cache(maxsize=4)
def _model(env_id: str) -> Any:
    from pidlab.plant.model import load_model

    return load_model(env_id)


def _quiet(progress: Progress | None) -> Progress:
    return progress if progress is not None else (lambda stage, fraction: None)


@dataclass(frozen=True)
class RoaPreview:
    """A region-of-attraction estimate with trajectories recorded in two variables.

    Attributes
    ----------
    roa : pidlab.region.roa.RegionOfAttraction
    variables : (str, str)
        The slice's variables.
    paths : tuple of ndarray, shape (steps, 2)
    recovered : tuple of bool
    """

    roa: Any
    variables: tuple[str, str]
    paths: tuple[np.ndarray, ...]
    recovered: tuple[bool, ...]


def slice_variables(spec: CoachSpec) -> tuple[str, str]:
    """The two variables of the ROA slice: the first loop's signal and its rate signal."""
    lp = spec.loops[0]
    return lp.signal, lp.rate_signal or lp.signal


def roa_preview(
    spec: CoachSpec, samples: int = ROA_PREVIEW_SAMPLES, progress: Progress | None = None
) -> RoaPreview:
    """Estimate the region of attraction of ``spec`` with a preview budget, keeping trajectories."""
    from pidlab.region.roa import estimate_roa

    loaded = _model(spec.env_id)
    variables = slice_variables(spec)
    roa, kept = estimate_roa(
        spec,
        loaded,
        samples=samples,
        bisection_samples=30,
        keep_trajectories=ROA_PREVIEW_TRAJECTORIES,
        record=variables,
        progress=_quiet(progress),
        workers=1,  # a job already runs on one of the app's worker processes
    )
    return RoaPreview(
        roa=roa,
        variables=variables,
        paths=tuple(np.asarray(k.path, dtype=float) for k in kept),
        recovered=tuple(bool(k.recovered) for k in kept),
    )


@dataclass(frozen=True)
class RolloutPreview:
    """The coach alone on the real env: its score and an animation of one episode.

    Attributes
    ----------
    mean, std : float
        Return over :attr:`episodes` seeded episodes (seeds 0..episodes-1).
    episodes : int
    mean_length : float
        Env steps per episode.
    causes : dict of str to int
        How the episodes ended.
    gif : bytes
        Animated GIF of the episode with seed 0.
    backend, note : str
        How the frames were drawn (``mujoco`` or ``schematic``) and why.
    """

    mean: float
    std: float
    episodes: int
    mean_length: float
    causes: dict[str, int]
    gif: bytes
    backend: str
    note: str


def rollout_preview(
    spec: CoachSpec,
    episodes: int = ROLLOUT_EPISODES,
    backend: str = "auto",
    progress: Progress | None = None,
) -> RolloutPreview:
    """Score the coach alone and draw an animation of its first episode.

    Each episode is :func:`pidlab.controller.animation.record_rollout` (the same episode as
    :func:`pidlab.controller.rollout.coach_alone` for the seed), so the animated one is not run twice.
    """
    from pidlab.controller.animation import frames_to_gif, record_rollout, render_frames

    report = _quiet(progress)
    loaded = _model(spec.env_id)
    returns: list[float] = []
    lengths: list[int] = []
    causes: dict[str, int] = {}
    first = None
    for i in range(episodes):
        report(f"episode {i + 1}/{episodes}", i / (episodes + 1))
        ep = record_rollout(spec, loaded, seed=i)
        first = first or ep
        returns.append(ep.total_return)
        lengths.append(ep.length)
        causes[ep.cause] = causes.get(ep.cause, 0) + 1
    if first is None:
        raise PidlabError(f"episodes={episodes}: expected 1 or more", param="episodes")
    report("drawing the rollout", episodes / (episodes + 1))
    frames = render_frames(loaded, first.qpos, backend=backend)
    return RolloutPreview(
        mean=float(np.mean(returns)),
        std=float(np.std(returns)),
        episodes=episodes,
        mean_length=float(np.mean(lengths)),
        causes=causes,
        gif=frames_to_gif(frames),
        backend=frames.backend,
        note=frames.note,
    )


def autotune_job(env_id: str, bandwidth: float, phase_margin: float, progress: Progress | None = None) -> Any:
    """Auto-tune (robust preset) for the asked crossover and phase margin.

    Runs :func:`pidlab.controller.autotune.tune`.
    """
    from pidlab.controller.autotune import tune

    report = _quiet(progress)
    budget = 400

    def count(n: int) -> None:
        report(f"auto-tuning ({n} evaluations)", min(n / budget, 1.0))

    return tune(
        _model(env_id),
        bandwidth=bandwidth,
        phase_margin=phase_margin,
        preset="robust",
        max_evaluations=budget,
        progress=count,
        workers=1,  # a job already runs on one of the app's worker processes
    )


@dataclass(frozen=True)
class BoundsResult:
    """Certified region and the critical bounds derived from it."""

    roa: Any
    bounds: Any
    variables: tuple[str, str]


def bounds_job(
    spec: CoachSpec, samples: int = BOUNDS_SAMPLES, progress: Progress | None = None
) -> BoundsResult:
    """What ``pidlab bounds SPEC`` does: certify the region with ``samples`` states, derive bounds."""
    from pidlab.region.bounds import derive_bounds
    from pidlab.region.roa import estimate_roa

    report = _quiet(progress)
    loaded = _model(spec.env_id)
    roa, _ = estimate_roa(spec, loaded, samples=samples, progress=report, workers=1)
    report("one-step check of the bounds", None)
    crit = derive_bounds(roa, spec, loaded, workers=1)
    return BoundsResult(roa=roa, bounds=crit, variables=slice_variables(spec))


JOBS: dict[str, Callable[..., Any]] = {
    "roa": roa_preview,
    "rollout": rollout_preview,
    "autotune": autotune_job,
    "bounds": bounds_job,
}


# --------------------------------------------------------------------------------------------
# Worker side


def _end_with(parent: int, by_kernel: bool) -> None:
    """End this process the moment ``parent`` (the server) dies, even by SIGKILL.

    A job has nothing to save, so the kernel's SIGKILL on the parent's death (Linux) ends it at
    once; elsewhere, and should the signal not come, a thread polling every 0.2 s ends it. The
    kernel's signal follows the *thread* that started this process, so it is asked for only when
    that was the main thread (``by_kernel``), which lives as long as the server.
    """
    if by_kernel:
        signal_on_parent_death(signal.SIGKILL)
    if os.getppid() != parent:  # the server died before the request above
        os._exit(0)
    watch_parent(lambda: os._exit(0), period_s=0.2)


def _init_worker(parent: int, by_kernel: bool) -> None:
    # headless offscreen rendering; must be set before mujoco is imported in this process
    if not os.environ.get("DISPLAY"):
        os.environ.setdefault("MUJOCO_GL", "egl")
    try:
        os.nice(10)  # the server process answers slider moves first
    except OSError:  # pragma: no cover
        pass
    _end_with(parent, by_kernel)


def _init_manager(parent: int, by_kernel: bool) -> None:
    _end_with(parent, by_kernel)


def _ready() -> bool:
    """A no-op job: returns once a worker process is up."""
    return True


def _run(
    job_id: int, kind: str, args: tuple[Any, ...], kwargs: dict[str, Any], updates: Any, cancel: Any
) -> Any:
    def progress(stage: str, fraction: float | None) -> None:
        if cancel.is_set():
            raise JobCancelled
        updates.put((job_id, stage, fraction))

    try:
        return ("ok", JOBS[kind](*args, progress=progress, **kwargs))
    except JobCancelled:
        return ("cancelled", None)
    except PidlabError as exc:
        return ("error", str(exc))
    except Exception as exc:  # a bug: keep the worker and the page alive, log the traceback
        return ("crash", f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}")


# --------------------------------------------------------------------------------------------
# Server side


@dataclass
class Job:
    """One submitted job, as the server sees it."""

    id: int
    kind: str
    future: Future[Any]
    cancel: Any
    stage: str = "queued"
    fraction: float | None = 0.0


@dataclass(frozen=True)
class JobUpdate:
    """What happened to a job since the last poll.

    Attributes
    ----------
    job_id : int
    kind : str
    state : {"running", "done", "error", "cancelled"}
    stage : str
        Progress text (running) or the error message (error).
    fraction : float or None
    result : object
        The job function's return value (done).
    """

    job_id: int
    kind: str
    state: str
    stage: str = ""
    fraction: float | None = None
    result: Any = None


@dataclass
class JobRunner:
    """A pool of worker processes running at most one job per (owner, kind) at a time.

    The owner is a tuner session: sessions sharing a runner do not abandon each other's jobs.
    While :attr:`held` is True (a server opening tabs) the tuners start no background jobs of
    their own accord; what the user asks for (auto-tune, bounds) still starts.
    """

    workers: int = 2
    held: bool = False
    _next: Any = field(default_factory=lambda: itertools.count(1))
    _jobs: dict[tuple[str, str], Job] = field(default_factory=dict)
    _latest: dict[int, tuple[str, float | None]] = field(default_factory=dict)
    _pool: ProcessPoolExecutor | None = None
    _manager: Any = None
    _updates: Any = None

    def start(self) -> None:
        """Start the manager and the worker processes now (otherwise the first job starts them).

        Starting takes a second or two (new Python processes); a server does it before it serves.
        """
        pool, _ = self._start()
        for future in [pool.submit(_ready) for _ in range(self.workers)]:
            future.result()

    def _start(self) -> tuple[ProcessPoolExecutor, Any]:
        """The worker pool and the manager, started on first use."""
        ctx = mp.get_context("spawn")
        # the processes are started by this thread: the kernel may end them with the process
        # only if this thread lives as long as it (see _end_with)
        started_by = (os.getpid(), threading.current_thread() is threading.main_thread())
        if self._manager is None:
            manager = SyncManager(ctx=ctx)
            manager.start(initializer=_init_manager, initargs=started_by)
            self._manager = manager
            self._updates = manager.Queue()
        if self._pool is None:
            self._pool = ProcessPoolExecutor(
                max_workers=self.workers, mp_context=ctx, initializer=_init_worker, initargs=started_by
            )
        return self._pool, self._manager

    def _new_pool(self) -> ProcessPoolExecutor:
        """A fresh worker pool in place of one a dead worker broke (the manager and its queue stay)."""
        broken, self._pool = self._pool, None
        if broken is not None:
            broken.shutdown(wait=False, cancel_futures=True)
        return self._start()[0]

    def submit(self, owner: str, kind: str, *args: Any, **kwargs: Any) -> int:
        """Start a ``kind`` job (a key of :data:`JOBS`) for ``owner``, abandoning its previous one.

        Returns
        -------
        int
            The job's id; its updates carry it.
        """
        pool, manager = self._start()
        self.cancel(owner, kind)
        job_id = next(self._next)
        cancel = manager.Event()
        try:
            future = pool.submit(_run, job_id, kind, args, kwargs, self._updates, cancel)
        except BrokenProcessPool:  # a worker died (killed, or out of memory): the next job gets new ones
            future = self._new_pool().submit(_run, job_id, kind, args, kwargs, self._updates, cancel)
        self._jobs[(owner, kind)] = Job(job_id, kind, future, cancel)
        return job_id

    def cancel(self, owner: str, kind: str | None = None) -> None:
        """Abandon ``owner``'s job of ``kind`` (every kind: None); a queued one never starts."""
        for key in [k for k in self._jobs if k[0] == owner and kind in (None, k[1])]:
            old = self._jobs.pop(key)
            old.cancel.set()
            old.future.cancel()

    def running(self, owner: str, kind: str) -> bool:
        """Whether ``owner`` has a job of ``kind`` queued or running."""
        return (owner, kind) in self._jobs

    def poll(self, owner: str) -> list[JobUpdate]:
        """``owner``'s progress and results since its last call (never blocks)."""
        if self._pool is None:
            return []
        while True:
            try:
                job_id, stage, fraction = self._updates.get_nowait()
            except queue_mod.Empty:
                break
            except (EOFError, OSError):  # the manager went away (shutdown)
                return []
            self._latest[job_id] = (stage, fraction)
        out = []
        for (who, kind), job in list(self._jobs.items()):
            if who != owner:
                continue
            if job.id in self._latest:
                job.stage, job.fraction = self._latest.pop(job.id)
                out.append(JobUpdate(job.id, kind, "running", job.stage, job.fraction))
            if not job.future.done():
                continue
            del self._jobs[(who, kind)]
            if job.future.cancelled():
                out.append(JobUpdate(job.id, kind, "cancelled"))
                continue
            try:
                status, value = job.future.result()
            except BrokenProcessPool:  # its worker, or another one of the pool, died
                status, value = "lost", (
                    f"the {kind} job's worker process died (killed by a signal, or by the system out of "
                    "memory); start it again"
                )
            except Exception as exc:  # the job could not reach its worker (or come back from it)
                status, value = "crash", f"{type(exc).__name__}: {exc}"
            if status == "ok":
                out.append(JobUpdate(job.id, kind, "done", result=value))
            elif status == "cancelled":
                out.append(JobUpdate(job.id, kind, "cancelled"))
            else:
                if status == "crash":
                    log.error("%s job failed:\n%s", kind, value)
                    value = f"internal error in the {kind} job: {str(value).splitlines()[0]}"
                out.append(JobUpdate(job.id, kind, "error", stage=str(value)))
        return out

    def shutdown(self) -> None:
        """Abandon every job and stop the workers."""
        for owner, kind in list(self._jobs):
            self.cancel(owner, kind)
        if self._pool is not None:
            # the workers must finish (abandoned jobs return at their next progress report)
            # while the manager still serves their queue and events; a job stuck in a long
            # step without reports is terminated after the grace period
            pool = self._pool
            waiter = threading.Thread(target=pool.shutdown, kwargs={"wait": True, "cancel_futures": True})
            waiter.start()
            waiter.join(timeout=10.0)
            if waiter.is_alive():
                for proc in list(getattr(pool, "_processes", {}).values()):
                    proc.terminate()
                waiter.join(timeout=5.0)
            self._pool = None
        if self._manager is not None:
            self._manager.shutdown()
            self._manager = None
