#!/usr/bin/env bash
# The main job: set up, then run the pipeline on InvertedPendulum-v5: linearization, the shipped
# coaches analysed (margins, poles, responses, score), then a small coaching experiment: PPO
# trained without a coach, with the paper's and with pidlab's (3 seeds each, 20k env steps),
# evaluated alone, and a report (out/experiment/report.md). A second run skips finished runs.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export PATH="$PWD/.venv/bin:$PATH"
pidlab linearize InvertedPendulum-v5
pidlab linearize InvertedPendulum-v5 --discrete
pidlab analyze tuning/InvertedPendulum-v5.paper.toml --episodes 10 --plots out/InvertedPendulum-v5.paper
pidlab analyze tuning/InvertedPendulum-v5.pidlab-robust.toml --episodes 10 --plots out/InvertedPendulum-v5.pidlab-robust

# A small coaching experiment: 3 seeds x 3 conditions, 20k env steps each, then its report
# (the full experiments are benchmarks/experiments.sh). Killed, the same command resumes.
pidlab experiment --envs InvertedPendulum-v5 --conditions none,paper,pidlab --seeds 3 --steps 20000 \
    --out out/experiment
