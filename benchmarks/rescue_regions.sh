#!/usr/bin/env bash
# The shipped rescue regions: tuning/ENV.pidlab-rescue.toml for the four paper envs, each with its
# certified core ([bounds], pidlab bounds) and its rescue region ([bounds.rescue], pidlab rescue) as its
# takeover region, and the region's figure in docs/images/rescue/. The pendulums get a coach tuned for
# room (pidlab tune --preset room); Hopper and Walker2d keep their robust coach (the room preset needs a
# linear design that measures the state). Then docs/rescue.md's table is regenerated from the specs.
# Usage: bash benchmarks/rescue_regions.sh [ENV ...]   (about 25 min on 2 cores for all four)
set -euo pipefail
cd "$(dirname "$0")/.."
envs=("$@")
[ ${#envs[@]} -gt 0 ] || envs=(InvertedPendulum-v5 InvertedDoublePendulum-v5 Hopper-v5 Walker2d-v5)
for env in "${envs[@]}"; do
    spec="tuning/$env.pidlab-rescue.toml"
    start=$(date +%s)
    case "$env" in
        InvertedPendulum-v5|InvertedDoublePendulum-v5)
            .venv/bin/pidlab tune "$env" --auto --preset room --name pidlab-rescue --workers 2 --force --output "$spec"
            .venv/bin/pidlab bounds "$spec" --write --workers 2 ;;
        *)
            .venv/bin/python -c "import sys, dataclasses; from pidlab.controller.spec import load_spec, save_spec
s = load_spec(sys.argv[1]); save_spec(dataclasses.replace(s, name='pidlab-rescue', description=s.description
    + ' Its rescue region (pidlab rescue) is its takeover region.'), sys.argv[2])" "tuning/$env.pidlab-robust.toml" "$spec" ;;
    esac
    .venv/bin/pidlab rescue "$spec" --write --plots "docs/images/rescue/$env" --workers 2
    echo "$env: $(( $(date +%s) - start )) s"
done
.venv/bin/python benchmarks/rescue_table.py
