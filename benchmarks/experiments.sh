#!/usr/bin/env bash
# The early-phase coaching experiments of docs/results/ENV (the issue-9 conditions; cut budgets on
# three envs): run them, then copy their reports into docs/. Each command resumes when run again
# (finished runs are skipped). The evidence at budgets where the uncoached agent reaches the target
# is benchmarks/evidence.sh. Budgets: see docs/results/README.md.
#   bash benchmarks/experiments.sh
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export PATH="$PWD/.venv/bin:$PATH"
conditions=none,paper,pidlab,pidlab-fading

run() {  # run ENV SEEDS [--steps N]: the experiment, then its report copied to docs/results/ENV
    local env=$1 seeds=$2
    shift 2
    local out="results/$env"
    pidlab experiment --envs "$env" --conditions "$conditions" --seeds "$seeds" --out "$out" "$@"
    mkdir -p "docs/results/$env"
    cp -r "$out/report.md" "$out/report.html" "$out/metrics.csv" "$out/summary.csv" "$out/figures" \
        "$out/experiment.json" \
        "docs/results/$env/"
    bash benchmarks/copy_runs.sh "$out" "docs/results/$env"
}

run InvertedPendulum-v5 10                        # full budget (100k env steps)
run InvertedDoublePendulum-v5 5 --steps 50000     # budget cut from 1,000,000 env steps
run Hopper-v5 5 --steps 25000                     # budget cut from 1,000,000 env steps
run Walker2d-v5 5 --steps 25000                   # budget cut from 1,000,000 env steps
.venv/bin/python benchmarks/results_table.py      # the tables of docs/results/README.md
.venv/bin/python benchmarks/recompute.py          # every published table, recomputed from the runs' logs
