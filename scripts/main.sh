#!/usr/bin/env bash
# The main job: set up, then run the pipeline on InvertedPendulum-v5.
# Today: linearization, then the shipped coaches analysed (margins, poles, responses, score).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export PATH="$PWD/.venv/bin:$PATH"
pidlab linearize InvertedPendulum-v5
pidlab linearize InvertedPendulum-v5 --discrete
pidlab analyze tuning/InvertedPendulum-v5.paper.toml --episodes 10 --plots out/InvertedPendulum-v5.paper
pidlab analyze tuning/InvertedPendulum-v5.pidlab-robust.toml --episodes 10 --plots out/InvertedPendulum-v5.pidlab-robust
