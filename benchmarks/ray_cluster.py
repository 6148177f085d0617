"""Does a sweep run on a Ray cluster? Start a local one with ``ray start --head``, join it, compare.

Starts a one-node Ray cluster (``ray start --head``, as on a cluster's head node), runs a small
coaching sweep on it with ``pidlab experiment --backend ray --address HOST:PORT``, runs the same
sweep with the default process pool, stops the cluster, and checks that every run's episode and
evaluation logs are identical byte for byte (same seed, same result, whichever backend ran it).
Writes what it did, with the wall times, to docs/results/ray-cluster.md and prints it:

    .venv/bin/python benchmarks/ray_cluster.py [--out results/ray-cluster]

The full design of docs/results/README.md runs on a real cluster the same way:
``bash benchmarks/evidence.sh -- --backend ray --address HOST:PORT``, with pidlab installed on
every node and results/ on a file system every node sees at the same path.
Exit status: 0 the logs are identical, 1 they differ, 2 the cluster or a sweep failed.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from bench_cli import Parser, run

from pidlab.files import atomic_write_text

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
PAGE = ROOT / "docs" / "results" / "ray-cluster.md"
PORT = 6380
SWEEP = ["--envs", "InvertedPendulum-v5", "--conditions", "none,rescue-terminal", "--seeds", "2",
         "--steps", "5000", "--no-progress"]  # fmt: skip
LOGS = ("episodes.csv", "evaluations.csv")


AUTH = {**os.environ, "RAY_AUTH_MODE": "token"}
"""Ray's token authentication for the cluster and the sweep that joins it (the token: ~/.ray/auth_token)."""


def _timed(cmd: list[str]) -> tuple[subprocess.CompletedProcess[str], float]:
    started = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, env=AUTH)
    return done, time.perf_counter() - started


def _shown(cmd: list[str]) -> str:
    return " ".join([Path(cmd[0]).name, *cmd[1:]])


def _same_logs(a: Path, b: Path) -> tuple[int, list[str]]:
    """Log files compared, and those that differ (or are missing on one side)."""
    files = sorted(p.relative_to(a) for name in LOGS for p in (a / "runs").glob(f"*/*/*/{name}"))
    differ = [str(f) for f in files if not (b / f).exists() or (a / f).read_bytes() != (b / f).read_bytes()]
    return len(files), differ


def _sweep(out: Path, backend: list[str]) -> tuple[list[str], subprocess.CompletedProcess[str], float]:
    shutil.rmtree(out, ignore_errors=True)
    cmd = [str(BIN / "pidlab"), "experiment", *SWEEP, "--out", os.path.relpath(out, ROOT), *backend]
    done, wall = _timed(cmd)
    return cmd, done, wall


def main(argv: list[str]) -> int:
    """Run the check; write and print the page."""
    parser = Parser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="results/ray-cluster", help="folder for the two sweeps")
    out = ROOT / parser.parse_args(argv).out
    head = [str(BIN / "ray"), "start", "--head", f"--port={PORT}", "--num-cpus=2",
            "--include-dashboard=false", "--disable-usage-stats"]  # fmt: skip
    token = [str(BIN / "ray"), "get-auth-token", "--generate"]  # creates ~/.ray/auth_token if missing
    if (made := subprocess.run(token, capture_output=True, text=True, cwd=ROOT)).returncode != 0:
        print(f"ray_cluster: `{_shown(token)}` failed: {made.stderr.strip()[-300:]}", file=sys.stderr)
        return 2
    started, start_s = _timed(head)
    if started.returncode != 0:
        why = (started.stderr.strip().splitlines() or ["no message"])[-1]
        print(f"ray_cluster: `{_shown(head)}` failed: {why}", file=sys.stderr)
        return 2
    try:
        on_ray = _sweep(out / "ray", ["--backend", "ray", "--address", f"127.0.0.1:{PORT}"])
    finally:
        stopped, _ = _timed([str(BIN / "ray"), "stop"])
    on_pool = _sweep(out / "process", ["--workers", "2"])
    for cmd, done, _ in (on_ray, on_pool):
        if done.returncode != 0:
            print(f"ray_cluster: `{_shown(cmd)}` exited {done.returncode}: {done.stderr.strip()[-500:]}",
                  file=sys.stderr)  # fmt: skip
            return 2
    compared, differ = _same_logs(out / "ray", out / "process")
    page = _page(head, start_s, on_ray, on_pool, stopped.returncode, compared, differ)
    atomic_write_text(PAGE, page)
    print(page)
    return 1 if differ or not compared else 0


def _page(head: list[str], start_s: float, on_ray: tuple, on_pool: tuple, stop_code: int, compared: int,
          differ: list[str]) -> str:  # fmt: skip
    import ray

    same = f"identical: all {compared} log files (episodes.csv, evaluations.csv of 4 runs) match exactly"
    verdict = same if compared and not differ else f"DIFFERENT: {', '.join(differ) or 'no logs'}"
    return "\n".join([
        "# A sweep on a Ray cluster", "",
        "Written by `.venv/bin/python benchmarks/ray_cluster.py` (Ray " + ray.__version__ + "). It starts a "
        "one-node cluster the way a cluster's head node is started, runs a small sweep on it through "
        "`--address`, runs the same sweep on the local process pool, and compares the runs' logs.", "",
        "Both run with `RAY_AUTH_MODE=token` (Ray's token authentication; the token is "
        "`~/.ray/auth_token`, made by `ray get-auth-token --generate` when missing): a driver without "
        "the token is refused by a cluster that has one.", "",
        "| step | command | exit | wall time |", "|---|---|---|---|",
        f"| start the cluster | `{_shown(head)}` | 0 | {start_s:.1f} s |",
        f"| sweep on the cluster | `{_shown(on_ray[0])}` | {on_ray[1].returncode} | {on_ray[2]:.1f} s |",
        f"| stop the cluster | `ray stop` | {stop_code} | |",
        f"| the same sweep, process pool | `{_shown(on_pool[0])}` | {on_pool[1].returncode} "
        f"| {on_pool[2]:.1f} s |",
        "", f"Logs of the two sweeps: {verdict}.", "",
        "The full design of [the results](README.md) on a cluster: start Ray on the head node "
        "(`ray start --head --port=6379`) and on every worker node (`ray start --address=HEAD:6379`), "
        "each with `RAY_AUTH_MODE=token` and the same token (copy `~/.ray/auth_token`, or set "
        "`RAY_AUTH_TOKEN`), with pidlab installed on each node (`bash scripts/setup.sh`) and the clone on "
        "a file system every node sees at the same path; then, on the head node:", "",
        "    RAY_AUTH_MODE=token bash benchmarks/evidence.sh -- --backend ray --address HEAD:6379", "",
        "Each run is one Ray task with one CPU and writes its own run directory under `results/`; a sweep "
        "that is stopped resumes from its runs' checkpoints when the same command is run again.", "",
    ])  # fmt: skip


if __name__ == "__main__":
    run(lambda: main(sys.argv[1:]))
