"""Independent tasks (simulations, optimizer starts, rollouts), spread over worker processes.

Every simulation of :mod:`pidlab.region` starts from a state chosen in advance (drawn from the
seed's random stream in the calling process, in a fixed order) and resets MuJoCo and the coach
first, so its outcome depends on its start state alone; each optimizer start of the CasADi
level estimate and of the auto-tuner's refinement likewise. A :class:`WorkerPool` runs such
tasks in order in-process (one worker) or spread over worker processes, each holding its own
copy of what the tasks need (e.g. a :class:`~pidlab.region.simulate.Simulator`): the same items
give the same results on any number of workers.

Most checks only ask whether *any* start state fails. :meth:`WorkerPool.run` can stop at the
first failure it finds (``stop``); which failures were found before it stopped depends on the
workers' timing, so callers use a stopped batch only as "it failed", never its counts.

The workers are forked where the platform allows (Linux: no start-up cost, nothing pickled) and
spawned elsewhere. They ignore Ctrl-C (the calling process decides), stop with the process that
started them (:func:`pidlab.orphans.stop_with_parent`), and are shut down when the pool closes.
On an error, an interrupt or a lost worker they are stopped at once, with nothing waited for (a
wait there could hang: see :meth:`WorkerPool._abandon`); a worker that died is one line,
:class:`~pidlab.errors.WorkerLostError`, not a traceback.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import os
import signal
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

from pidlab.checks import integer
from pidlab.errors import PidlabError, WorkerLostError

S = TypeVar("S")
T = TypeVar("T")
R = TypeVar("R")

MAX_WORKERS = 4
"""The most worker processes a pool starts by default (``workers=None``)."""

ABANDON_WAIT_S = 5.0
"""How long an abandoned pool waits for its executor's manager thread, which ends once it sees the
workers gone (it is not waited for beyond that: see :meth:`WorkerPool._abandon`)."""

MAX_WORKERS_ASKED = 256
"""The most worker processes a caller may ask for."""

CHUNKS_PER_WORKER = 8
"""A batch is cut into about this many chunks per worker (load balance against messaging)."""

WORKER_LOST = (
    "a worker process stopped abruptly (killed by a signal, or by the system out of memory), and the "
    "work in hand was lost; run it again (with one worker everything runs in this process)"
)
"""The message of :class:`~pidlab.errors.WorkerLostError` when a pool's worker dies."""


def resolve_workers(
    workers: int | None, error: type[PidlabError] = PidlabError, param: str = "workers"
) -> int:
    """The number of worker processes: ``workers``, or the machine's cores (at most :data:`MAX_WORKERS`).

    Raises
    ------
    PidlabError
        Of class ``error``: ``workers`` is not an integer from 1 to :data:`MAX_WORKERS_ASKED`.
    """
    if workers is None:
        return max(1, min(os.cpu_count() or 1, MAX_WORKERS))
    return integer(workers, param, error, low=1, high=MAX_WORKERS_ASKED, param=param)


def pool_context() -> Any:
    """The multiprocessing context of the pools: fork where available, else spawn."""
    return mp.get_context("fork" if "fork" in mp.get_all_start_methods() else "spawn")


# --------------------------------------------------------------------------------------------
# The worker side


_worker_state: Any = None
_worker_stop: Any = None


def _init_worker(build: Callable[..., Any], args: tuple[Any, ...], stop: Any, parent: int) -> None:
    """Worker set-up: its state ``build(*args)``; Ctrl-C left to the parent; stop with the parent.

    A worker is one of the processes that share the cores, so its BLAS library runs on one thread:
    left at the library's default (one thread per core), the workers' matrix products would wait
    on each other, as training's did (:func:`pidlab.rl.train._run`).
    """
    from threadpoolctl import threadpool_limits

    from pidlab.orphans import stop_with_parent

    global _worker_state, _worker_stop
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    stop_with_parent(parent, lambda: os.kill(os.getpid(), signal.SIGTERM))
    _worker_state = build(*args)
    threadpool_limits(1, "blas")  # for the worker's life (it is not restored)
    _worker_stop = stop


def _run_chunk(
    task: Callable[[Any, T], R], items: Sequence[T], stop: Callable[[R], bool] | None
) -> tuple[list[R], bool]:
    """``(results, stopped)`` of ``task`` over ``items`` in this worker, up to the first ``stop``."""
    return _run_items(_worker_state, task, items, stop, _worker_stop)


def _run_items(
    state: S,
    task: Callable[[S, T], R],
    items: Sequence[T],
    stop: Callable[[R], bool] | None,
    flag: Any = None,
) -> tuple[list[R], bool]:
    """``(results, stopped)``: ``task(state, item)`` in order, up to the first result ``stop`` accepts.

    ``flag`` (an event) set by the calling process abandons the rest too (``stopped`` True).
    """
    out: list[R] = []
    for item in items:
        if flag is not None and flag.is_set():
            return out, True
        result = task(state, item)
        out.append(result)
        if stop is not None and stop(result):
            return out, True
    return out, False


# --------------------------------------------------------------------------------------------
# The calling side


@dataclass(frozen=True)
class Batch(Generic[R]):
    """What :meth:`WorkerPool.run` returns.

    Attributes
    ----------
    results : list
        Complete and in item order when not :attr:`stopped`; otherwise those found before the
        stop (in item order), the first stopping one among them.
    stopped : bool
        Whether a result was accepted by ``stop`` (the rest were abandoned).
    """

    results: list[R]
    stopped: bool


class WorkerPool(Generic[S]):
    """Tasks on a state ``build(*args)``, in-process or over worker processes holding their own.

    Parameters
    ----------
    build : callable
        Makes the state the tasks run on (once per worker; in-process on first need). A
        module-level callable, e.g. a class.
    args : tuple
        Its arguments (inherited by forked workers, pickled for spawned ones).
    workers : int, optional
        Worker processes (default: the machine's cores, at most :data:`MAX_WORKERS`); 1 runs
        everything in this process. The workers start on the first batch worth spreading.

    Use it as a context manager (or call :meth:`close`): the workers are stopped on exit.
    """

    def __init__(self, build: Callable[..., S], args: tuple[Any, ...], workers: int | None = None) -> None:
        self.workers = resolve_workers(workers)
        self._build = build
        self._args = args
        self._local: S | None = None
        self._executor: ProcessPoolExecutor | None = None
        self._stop: Any = None

    def __enter__(self) -> WorkerPool[S]:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        if exc_type is None:
            self.close()
        else:  # an error or an interrupt, also between batches: nothing is waited for
            self._abandon()

    @property
    def state(self) -> S:
        """The state in this process (built on first use)."""
        if self._local is None:
            self._local = self._build(*self._args)
        return self._local

    def close(self) -> None:
        """Stop the workers (they finish the task in hand); idempotent."""
        executor, self._executor = self._executor, None
        if executor is not None:
            self._stop.set()
            executor.shutdown(wait=True, cancel_futures=True)

    def _start(self) -> ProcessPoolExecutor:
        if self._executor is None:
            ctx = pool_context()
            self._stop = ctx.Event()
            self._executor = ProcessPoolExecutor(
                max_workers=self.workers,
                mp_context=ctx,
                initializer=_init_worker,
                initargs=(self._build, self._args, self._stop, os.getpid()),
            )
        return self._executor

    def run(
        self,
        task: Callable[[S, T], R],
        items: Sequence[T],
        stop: Callable[[R], bool] | None = None,
        tick: Callable[[int], None] | None = None,
    ) -> Batch[R]:
        """``task(state, item)`` for every item; with ``stop``, until a result that it accepts.

        Parameters
        ----------
        task : callable
            A module-level function, or a ``functools.partial`` of one (sent to the workers).
        items : sequence
            Picklable inputs, e.g. initial states.
        stop : callable, optional
            ``stop(result)``: true for a result that settles the batch (a failure); the other
            items may then be left undone. A module-level function.
        tick : callable, optional
            ``tick(done)`` with the number of items done so far (may raise to abandon the batch).

        Returns
        -------
        Batch

        Raises
        ------
        WorkerLostError
            A worker process died (killed, or out of memory); the pool starts new ones next time.
        """
        if self.workers == 1 or len(items) < 2:
            return self._run_here(task, items, stop, tick)
        return self._run_spread(task, items, stop, tick)

    def _run_here(
        self,
        task: Callable[[S, T], R],
        items: Sequence[T],
        stop: Callable[[R], bool] | None,
        tick: Callable[[int], None] | None,
    ) -> Batch[R]:
        results: list[R] = []
        for i, item in enumerate(items):
            if tick is not None:
                tick(i)
            done, stopped = _run_items(self.state, task, [item], stop)
            results += done
            if stopped:
                return Batch(results, True)
        return Batch(results, False)

    def _run_spread(
        self,
        task: Callable[[S, T], R],
        items: Sequence[T],
        stop: Callable[[R], bool] | None,
        tick: Callable[[int], None] | None,
    ) -> Batch[R]:
        executor = self._start()
        self._stop.clear()
        size = max(1, math.ceil(len(items) / (self.workers * CHUNKS_PER_WORKER)))
        futures: dict[Future[tuple[list[R], bool]], int] = {}
        try:
            for k in range(0, len(items), size):
                futures[executor.submit(_run_chunk, task, items[k : k + size], stop)] = k
            batch = _collect(futures, tick)
        except BrokenProcessPool:
            self._abandon()
            raise WorkerLostError(WORKER_LOST) from None
        except BaseException:
            self._abandon()  # an error or an interrupt: nothing more is waited for
            raise
        self._stop.set()  # a stop settled the batch: the chunks in hand return at their next item
        for f in futures:
            f.cancel()
        wait(futures)
        return batch

    def _abandon(self) -> None:
        """Stop the workers at once and drop the executor (the next batch starts new ones).

        Waiting for the chunks in hand could last forever: when the workers were killed with the
        caller (a signal to the process group), Python 3.11's executor fails to mark the futures
        it had not cancelled, and a wait on them never ends. So nothing is cancelled or waited
        for here: the workers are terminated, and the executor marks every future broken.
        Only the executor's manager thread is given :data:`ABANDON_WAIT_S` to end: it closes its
        wake-up pipe as it ends, and a command that exited while it did so had Python's exit hook
        write to that pipe as it closed (``OSError: [Errno 9] Bad file descriptor``, a traceback
        after ``pidlab: interrupted``).
        """
        executor, self._executor = self._executor, None
        if executor is None:
            return
        self._stop.set()
        processes = list(getattr(executor, "_processes", {}).values())  # not public before 3.14
        manager = getattr(executor, "_executor_manager_thread", None)
        executor.shutdown(wait=False)
        for process in processes:
            if process.is_alive():
                process.terminate()
        if manager is not None:  # it closes its pipes as it ends: at exit, Python must not write to them then
            manager.join(ABANDON_WAIT_S)


def _collect(
    futures: dict[Future[tuple[list[R], bool]], int], tick: Callable[[int], None] | None
) -> Batch[R]:
    """The chunks' results in item order (``futures``: each chunk's first item); early after a stop."""
    chunks: dict[int, list[R]] = {}
    pending = set(futures)
    done_items = 0
    stopped = False
    while pending and not stopped:
        finished, pending = wait(pending, return_when=FIRST_COMPLETED)
        for f in finished:
            results, chunk_stopped = f.result()
            chunks[futures[f]] = results
            done_items += len(results)
            stopped = stopped or chunk_stopped
        if tick is not None and not stopped:
            tick(done_items)
    return Batch([r for k in sorted(chunks) for r in chunks[k]], stopped)


def run_all(
    build: Callable[..., S],
    args: tuple[Any, ...],
    task: Callable[[S, T], R],
    items: Sequence[T],
    workers: int,
) -> list[R]:
    """``[task(build(*args), item) for item in items]``, spread over ``workers`` processes (in order).

    For a few independent, costly items (e.g. optimizer starts); the pool is closed on return.
    """
    with WorkerPool(build, args, workers) as pool:
        return pool.run(task, items).results
