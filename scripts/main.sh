#!/usr/bin/env bash
# The main job: set up, then the whole pipeline on InvertedPendulum-v5 (`pidlab run`):
# linearize -> auto-tune a coach -> certify its region of attraction and derive critical bounds ->
# train PPO with and without the coach (the recipe's [pipeline] table: 3 seeds, 30,000 env steps)
# -> one report (out/InvertedPendulum-v5/report.html, with report.md and PNG figures).
# Options are passed on to `pidlab run` (e.g. --steps 5000 --seeds 1). Killed, the same command resumes.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/pidlab run InvertedPendulum-v5 "$@"
