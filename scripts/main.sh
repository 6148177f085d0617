#!/usr/bin/env bash
# The main job: set up, then run the pipeline on InvertedPendulum-v5.
# Today the pipeline is its first stage: linearization and analysis.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export PATH="$PWD/.venv/bin:$PATH"
pidlab linearize InvertedPendulum-v5
pidlab linearize InvertedPendulum-v5 --discrete
