#!/usr/bin/env bash
# Learning per env step with 1 env and with vectorized envs (issue 19): the uncoached agent of each
# recipe variant in benchmarks/vectorization/, 10 seeds on InvertedPendulum-v5 (50k env steps) and
# 5 seeds on Hopper-v5 (100k env steps). Resumes when run again. Then:
#   .venv/bin/python benchmarks/vectorization.py     # the comparison, written to docs/vectorization.md
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export PATH="$PWD/.venv/bin:$PATH"
for n in n1 n8 n4; do  # n4 was added after n8 turned out worse (docs/vectorization.md)
    pidlab experiment --envs InvertedPendulum-v5 --conditions none --seeds 10 --steps 50000 --no-progress \
        --recipe "benchmarks/vectorization/InvertedPendulum-v5.$n.toml" --out "results/vectorization/InvertedPendulum-v5.$n"
done
for n in n1-b32 n8-b32; do
    pidlab experiment --envs Hopper-v5 --conditions none --seeds 5 --steps 100000 --no-progress \
        --recipe "benchmarks/vectorization/Hopper-v5.$n.toml" --out "results/vectorization/Hopper-v5.$n"
done
