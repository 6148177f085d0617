#!/usr/bin/env bash
# The main job: set up, then run the pipeline on InvertedPendulum-v5: linearization, the shipped
# coaches analysed (margins, poles, responses, score), then PPO trained with and without the
# pidlab-robust coach (30k env steps each) and evaluated alone. A second run resumes (and so
# skips) the training runs it finds finished in out/train/.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export PATH="$PWD/.venv/bin:$PATH"
pidlab linearize InvertedPendulum-v5
pidlab linearize InvertedPendulum-v5 --discrete
pidlab analyze tuning/InvertedPendulum-v5.paper.toml --episodes 10 --plots out/InvertedPendulum-v5.paper
pidlab analyze tuning/InvertedPendulum-v5.pidlab-robust.toml --episodes 10 --plots out/InvertedPendulum-v5.pidlab-robust

train() {  # train COACH: a new run in out/train/COACH, or resume the one there
    local dir="out/train/$1"
    if [ -f "$dir/config.toml" ]; then
        pidlab train InvertedPendulum-v5 --resume "$dir"
    else
        pidlab train InvertedPendulum-v5 --coach "$1" --steps 30000 --seed 0 --run-dir "$dir"
    fi
}
train none
train pidlab-robust
