"""The region stages over worker processes: the same results for any number of workers, no leaks."""

from __future__ import annotations

import os
import signal
import subprocess
import time

import mujoco
import numpy as np
import pytest

from pidlab.controller.analysis import analyze_coach
from pidlab.controller.autotune import tune
from pidlab.controller.pid import Coach
from pidlab.controller.spec import dumps_spec, load_spec, loads_spec
from pidlab.errors import RegionError
from pidlab.parallel import WorkerPool, resolve_workers
from pidlab.region.bounds import derive_bounds
from pidlab.region.roa import estimate_roa
from pidlab.region.simulate import SimulationPool
from tests.helpers import PAPER_ENVS, TUNING, cli_in_process


def _region_and_bounds(spec, loaded, workers, **budget):
    roa, kept = estimate_roa(spec, loaded, seed=3, workers=workers, **budget)
    crit = derive_bounds(roa, spec, loaded, check_samples=12, seed=3, workers=workers)
    return roa, kept, crit


def _same(a, b):
    roa1, kept1, crit1 = a
    roa2, kept2, crit2 = b
    for name in ("level", "c_optimization", "c_simulation", "check", "box", "method"):
        assert getattr(roa1, name) == getattr(roa2, name), name
    assert len(kept1) == len(kept2)
    for t1, t2 in zip(kept1, kept2, strict=True):
        assert t1.recovered == t2.recovered and np.array_equal(t1.path, t2.path)
    assert crit1.to_table() == crit2.to_table()


@pytest.mark.parametrize(
    ("env", "budget"),
    [
        (
            "InvertedPendulum-v5",
            {"samples": 60, "bisection_samples": 12, "bisection_rounds": 4, "horizon_s": 0.5},
        ),
        ("Hopper-v5", {"samples": 8, "bisection_samples": 4, "bisection_rounds": 3, "horizon_s": 0.2}),
    ],
)
def test_one_and_two_workers_give_the_same_region_and_bounds(models, env, budget):
    spec = load_spec(TUNING / f"{env}.pidlab-robust.toml")
    if env == "InvertedPendulum-v5":  # a derivative filter: the coach has a state, no CasADi estimate (fast)
        spec = loads_spec(dumps_spec(spec).replace("tf = 0.0", "tf = 0.01", 1))
    loaded = models[env]
    budget = {**budget, "keep_trajectories": 5, "record": (spec.loops[0].signal, spec.loops[0].rate_signal)}
    _same(_region_and_bounds(spec, loaded, 1, **budget), _region_and_bounds(spec, loaded, 2, **budget))


def test_casadi_starts_on_two_workers_give_the_same_level(models):
    from pidlab.region.roa import lyapunov_function, optimization_level

    spec = load_spec(TUNING / "InvertedPendulum-v5.pidlab-robust.toml")
    loaded = models["InvertedPendulum-v5"]
    coach = Coach(spec, loaded)
    analysis = analyze_coach(coach, loaded)
    with SimulationPool(spec, loaded, analysis.linearization, 1) as pool:
        lyap = lyapunov_function(analysis, coach, pool.sim.y_op)
    one, two = (
        optimization_level(
            spec, loaded, lyap, coach, analysis.linearization, 12, starts=6, c_scale=2.0, workers=w
        )
        for w in (1, 2)
    )
    assert one is not None and one == two


def test_refinement_on_two_workers_gives_the_same_coach(models):
    one, two = (tune(models["Hopper-v5"], max_evaluations=5, refine_evaluations=1, workers=w) for w in (1, 2))
    assert one.spec == two.spec and one.refined_return == two.refined_return
    assert one.evaluations == two.evaluations


def _pids(pool):
    return [p.pid for p in pool._executor._processes.values()]  # the executor's live workers


def _gone(pids, timeout=10.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        alive = []
        for pid in pids:
            try:
                os.kill(pid, 0)
                alive.append(pid)
            except ProcessLookupError:
                pass
        if not alive:
            return True
        time.sleep(0.05)
    return False


def _square(state, x):
    return state * x * x


def _fails_on_three(state, x):
    if x == 3:
        raise ValueError("three")
    return x


class _Stop(Exception):
    pass


def test_pools_stop_their_workers_on_exit_errors_and_interrupts():
    with WorkerPool(int, (2,), workers=2) as pool:
        assert pool.run(_square, list(range(10))).results == [2 * x * x for x in range(10)]
        pids = _pids(pool)
    assert len(pids) == 2 and _gone(pids)
    # an error in a task reaches the caller; the pool's workers still stop
    with pytest.raises(ValueError, match="three"), WorkerPool(int, (1,), workers=2) as pool:
        pool.run(_square, [1, 2])
        pids = _pids(pool)
        pool.run(_fails_on_three, list(range(8)))
    assert _gone(pids)

    # a progress callback that raises (a cancelled job, Ctrl-C) abandons the batch
    def cancel(done):
        raise _Stop

    with pytest.raises(_Stop), WorkerPool(int, (1,), workers=2) as pool:
        pool.run(_square, [1, 2])
        pids = _pids(pool)
        pool.run(_square, list(range(100)), tick=cancel)
    assert _gone(pids)


def _dies_on_five(state, x):
    if x == 5:
        os.kill(os.getpid(), signal.SIGKILL)  # as the system's out-of-memory killer would
    time.sleep(0.01)
    return x


def test_a_worker_that_dies_is_one_error_and_the_pool_starts_anew():
    """A worker killed mid-batch: WorkerLostError (one line), no hang; the next batch gets new workers."""
    from pidlab.errors import WorkerLostError

    with WorkerPool(int, (1,), workers=2) as pool:
        pool.run(_square, [1, 2])
        pids = _pids(pool)
        with pytest.raises(WorkerLostError, match=r"^a worker process stopped abruptly \(killed") as err:
            pool.run(_dies_on_five, list(range(40)))
        assert "\n" not in str(err.value) and _gone(pids)  # the other worker was stopped too
        assert pool.run(_square, [1, 2, 3]).results == [1, 4, 9]
        assert not set(_pids(pool)) & set(pids)


def _bounds_with_workers(tmp_path):
    """A real ``pidlab bounds`` in a session of its own, once its two workers run (a long job)."""
    import shutil
    import sys
    from pathlib import Path

    spec = tmp_path / "InvertedPendulum-v5.pidlab-robust.toml"
    shutil.copy(TUNING / spec.name, spec)
    pidlab = str(Path(sys.executable).with_name("pidlab"))
    cmd = [pidlab, "bounds", str(spec), "--samples", "200000", "--workers", "2"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:  # until its workers run
        children = subprocess.run(["pgrep", "-P", str(proc.pid)], capture_output=True, text=True).stdout.split()
        if len(children) >= 2:
            break
        time.sleep(0.2)
    else:
        proc.kill()
        pytest.fail("the command started no workers in time")
    time.sleep(1.0)
    return proc


def test_a_signal_to_the_whole_process_group_ends_a_command_at_once(tmp_path):
    """SIGTERM to the command and its workers together (a job control's kill): it exits 130 with one
    line, where Python 3.11's executor, left to mark futures it had cancelled, hung and printed a
    thread's traceback."""
    proc = _bounds_with_workers(tmp_path)
    os.killpg(proc.pid, signal.SIGTERM)
    try:
        _, stderr = proc.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        pytest.fail("the command hung after SIGTERM to its process group")
    assert proc.returncode == 130 and stderr.decode().strip() == "pidlab: interrupted"


def test_a_second_signal_as_the_command_ends_prints_no_traceback(tmp_path):
    """SIGTERM to the command, then to its process group (as ``timeout`` and job controls send it):
    the command ends with its one line. The second signal used to land in a weak reference's
    callback or Python's exit hook and print "Exception ignored in ..." with a traceback."""
    proc = _bounds_with_workers(tmp_path)
    os.kill(proc.pid, signal.SIGTERM)
    for _ in range(20):  # then to the group, again and again, as the command ends
        try:
            os.killpg(proc.pid, signal.SIGTERM)
        except ProcessLookupError:
            break
        time.sleep(0.05)
    try:
        _, stderr = proc.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        pytest.fail("the command hung after SIGTERM")
    assert proc.returncode == 130 and stderr.decode().strip() == "pidlab: interrupted", stderr.decode()


def test_an_interrupt_raised_in_a_finalizer_is_delivered_again():
    """While a command runs, a KeyboardInterrupt that a signal raised inside a ``__del__`` (which
    cannot propagate, so Python prints it and goes on) is sent again and stops the command."""
    from pidlab.interrupts import sigterm_interrupts

    class Finalized:
        def __del__(self):
            raise KeyboardInterrupt  # as a signal's handler raises it, wherever the main thread is

    with sigterm_interrupts(), pytest.raises(KeyboardInterrupt):
        Finalized()  # dropped at once: its __del__ runs here
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:  # the signal sent again arrives within milliseconds
            time.sleep(0.001)


def _blas_threads(state, item):
    from threadpoolctl import threadpool_info

    np.ones((64, 64)) @ np.ones((64, 64))  # the BLAS library is loaded and used
    return sorted({lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"})


def test_workers_run_blas_on_one_thread_and_leave_the_callers_alone():
    from threadpoolctl import threadpool_info, threadpool_limits

    with threadpool_limits(2, "blas"):
        before = _blas_threads(None, 0)
        with WorkerPool(int, (1,), workers=2) as pool:
            assert pool.run(_blas_threads, list(range(8))).results == [[1]] * 8
        assert _blas_threads(None, 0) == before
    assert before and all(lib["num_threads"] >= 1 for lib in threadpool_info())


def test_a_batch_stops_at_a_failure_and_is_complete_otherwise():
    for workers in (1, 2):
        with WorkerPool(int, (1,), workers=workers) as pool:
            batch = pool.run(_square, list(range(40)), stop=bool)
            # which failing chunk settles the batch first is a race between the workers:
            # any failure may be the one reported, and only squares of the items come back
            assert batch.stopped and any(batch.results)
            assert set(batch.results) <= {x * x for x in range(40)}
            batch = pool.run(_square, [0] * 40, stop=bool)
            assert not batch.stopped and batch.results == [0] * 40


def test_worker_counts_are_checked():
    assert 1 <= resolve_workers(None) <= 4
    with pytest.raises(RegionError, match=r"workers=0: expected"):
        resolve_workers(0, RegionError)
    code, stderr = cli_in_process(
        "bounds", str(TUNING / "InvertedPendulum-v5.pidlab-robust.toml"), "--workers", "0"
    )
    assert code == 2 and "--workers 0" in stderr and len(stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("env", PAPER_ENVS)
def test_simulator_observes_and_terminates_as_the_compiled_card(models, env):
    spec = load_spec(TUNING / f"{env}.pidlab-robust.toml")
    loaded = models[env]
    with SimulationPool(spec, loaded, analyze_coach(Coach(spec, loaded), loaded).linearization, 1) as pool:
        sim = pool.sim
        rng = np.random.default_rng(0)
        terminated = 0
        for _ in range(20):
            sim.start(rng.normal(0.0, 0.3, 2 * sim.m.nv))
            for _ in range(10):
                sim.d.ctrl[:] = rng.uniform(-1, 1, sim.m.nu)
                mujoco.mj_step(sim.m, sim.d, nstep=loaded.frame_skip)
                obs = sim.observe()
                assert obs.tobytes() == sim.fast.observe(sim.d).tobytes()
                assert sim.terminated(obs) == sim.fast.terminated(sim.d)
                terminated += sim.terminated(obs)
        assert terminated > 0  # the comparison covered terminal states too
