#!/usr/bin/env bash
# The test job: set up, lint, build the documentation, then run the whole test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
bash scripts/browser.sh
export PATH="$PWD/.venv/bin:$PATH"
ruff check pidlab tests benchmarks docs/hooks
mypy pidlab
# The documentation site, strictly: a broken link or anchor, a page missing from the nav, or a
# docstring griffe cannot read is an error. Not --quiet: it would hide the warnings from --strict
# too. Only the INFO lines are dropped. (NO_MKDOCS_2_WARNING: Material's banner about MkDocs 2.)
NO_MKDOCS_2_WARNING=1 mkdocs build --strict --site-dir build/site 2>&1 | { grep -v "^INFO " || true; }
# Two workers (CI machines have 2 cores): the suite is CPU-bound, one process per core.
python -m pytest -n 2 "$@"
