#!/usr/bin/env bash
# Copy a finished `pidlab run ENV` report into the docs: docs/results/pipeline-ENV/ gets report.md,
# report.html and figures/, and experiment/ gets the sweep's own report, figures, tables, record and
# each run's logs (checkpoints, models and TensorBoard files stay in out/). Usage: bash benchmarks/publish_pipeline.sh [ENV] [OUT]
set -euo pipefail
cd "$(dirname "$0")/.."
env="${1:-InvertedPendulum-v5}"
src="${2:-out/$env}"
dst="docs/results/pipeline-$env"
for f in report.md report.html experiment/report.md experiment/report.html; do
    [ -f "$src/$f" ] || { echo "publish_pipeline: $src/$f missing: run 'pidlab run $env' first" >&2; exit 2; }
done
rm -rf "$dst"
mkdir -p "$dst/experiment"
cp "$src/report.md" "$src/report.html" "$dst/"
cp -r "$src/figures" "$dst/figures"
cp "$src/experiment/report.md" "$src/experiment/report.html" "$src/experiment/metrics.csv" \
    "$src/experiment/summary.csv" "$src/experiment/experiment.json" "$dst/experiment/"
cp -r "$src/experiment/figures" "$dst/experiment/figures"
bash benchmarks/copy_runs.sh "$src/experiment" "$dst/experiment"
echo "published $src to $dst"
