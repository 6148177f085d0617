#!/usr/bin/env bash
# The test job: set up, lint, then run the whole test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
bash scripts/browser.sh
export PATH="$PWD/.venv/bin:$PATH"
ruff check pidlab tests benchmarks
mypy pidlab
python -m pytest "$@"
