#!/usr/bin/env bash
# Copy an experiment's per-run logs and records (no checkpoints, models or TensorBoard files) for
# publishing: SRC/runs/ENV/CONDITION/seed-S/{episodes.csv,evaluations.csv,summary.json,config.toml,
# coach.toml,run.json,timing.csv,warm_start.json,rollin.json,reused.json} to the same paths under DST, replacing DST/runs. benchmarks/recompute.py
# recomputes every published table from them. Usage: bash benchmarks/copy_runs.sh SRC DST
set -euo pipefail
src=$1 dst=$2
[ -d "$src/runs" ] || { echo "copy_runs: $src/runs: no such folder (run the experiment first)" >&2; exit 2; }
rm -rf "$dst/runs"
(cd "$src" && find runs -mindepth 4 -maxdepth 4 -type f \( -name episodes.csv -o -name evaluations.csv \
    -o -name summary.json -o -name config.toml -o -name coach.toml -o -name run.json -o -name timing.csv \
    -o -name warm_start.json -o -name rollin.json -o -name reused.json \) | sort) |
while read -r f; do
    mkdir -p "$dst/$(dirname "$f")"
    cp "$src/$f" "$dst/$f"
done
