#!/usr/bin/env bash
# The committed coaching experiments (docs/results/): run them, then copy their reports into docs/.
# Each command resumes when run again (finished runs are skipped). Budgets: see docs/results/README.md.
#   bash benchmarks/experiments.sh            # the budgets committed in docs/results/
#   FULL=1 bash benchmarks/experiments.sh     # every env at its recipe's full budget and 10 seeds
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export PATH="$PWD/.venv/bin:$PATH"
conditions=none,paper,pidlab,pidlab-fading

run() {  # run ENV SEEDS [--steps N]: the experiment, then its report copied to docs/results/ENV
    local env=$1 seeds=$2
    shift 2
    local out="results/$env${FULL:+-full}"
    pidlab experiment --envs "$env" --conditions "$conditions" --seeds "$seeds" --out "$out" "$@"
    if [ -z "${FULL:-}" ]; then
        mkdir -p "docs/results/$env"
        cp -r "$out/report.md" "$out/report.html" "$out/metrics.csv" "$out/summary.csv" "$out/figures" \
            "$out/experiment.json" \
            "docs/results/$env/"
        bash benchmarks/copy_runs.sh "$out" "docs/results/$env"
    fi
}

if [ -n "${FULL:-}" ]; then
    for env in InvertedPendulum-v5 InvertedDoublePendulum-v5 Hopper-v5 Walker2d-v5; do run "$env" 10; done
else
    run InvertedPendulum-v5 10                        # full budget (100k env steps)
    run InvertedDoublePendulum-v5 5 --steps 50000     # budget cut from 1,000,000 env steps
    run Hopper-v5 5 --steps 25000                     # budget cut from 1,000,000 env steps
    run Walker2d-v5 5 --steps 25000                   # budget cut from 1,000,000 env steps
    .venv/bin/python benchmarks/results_table.py      # the tables of docs/results/README.md
    .venv/bin/python benchmarks/recompute.py          # every published table, recomputed from the runs' logs
fi
