#!/usr/bin/env bash
# The model predictor's measurement per env: `pidlab forecast` on each pidlab-rescue spec writes
# tuning/ENV.pidlab-rescue-model.toml (and on InvertedPendulum's classifier region pidlab-rescue-edge,
# tuning/InvertedPendulum-v5.pidlab-rescue-edge-model.toml, and a learned model on InvertedDoublePendulum's,
# tuning/InvertedDoublePendulum-v5.pidlab-rescue-full-learned.toml) (the spec with its [bounds.forecast]: 5,000 actions of a random
# agent behind the exact shield set the margins, 5,000 more check them; seed 0), then
# benchmarks/forecast_table.py writes the table of docs/rescue.md from those files (and the training
# falls of docs/results/InvertedPendulum-v5-model, when published).
#
#   bash benchmarks/forecast.sh
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
for env in InvertedPendulum-v5 InvertedDoublePendulum-v5 Hopper-v5 Walker2d-v5; do
    .venv/bin/pidlab forecast "tuning/$env.pidlab-rescue.toml" --transitions 5000 --held-out 5000 --seed 0 \
        -o "tuning/$env.pidlab-rescue-model.toml" --force
done
# the classifier region validated at its edge (Amendment 14)
.venv/bin/pidlab forecast tuning/InvertedPendulum-v5.pidlab-rescue-edge.toml --transitions 5000 --held-out 5000 \
    --seed 0 -o tuning/InvertedPendulum-v5.pidlab-rescue-edge-model.toml --force
# a learned one-step model on InvertedDoublePendulum's classifier region (Amendment 15)
.venv/bin/pidlab forecast tuning/InvertedDoublePendulum-v5.pidlab-rescue-full.toml --model learned --fit 100000 \
    --width 128 --epochs 100 --transitions 5000 --held-out 5000 --seed 0 \
    -o tuning/InvertedDoublePendulum-v5.pidlab-rescue-full-learned.toml --force
.venv/bin/python benchmarks/forecast_table.py
