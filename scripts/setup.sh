#!/usr/bin/env bash
# Create .venv and install pidlab with the exact versions of requirements.lock.
# Idempotent: a second run with an unchanged lock file installs nothing.
set -euo pipefail
cd "$(dirname "$0")/.."

if [ ! -x .venv/bin/python ]; then
    PY="${PIDLAB_PYTHON:-}"
    if [ -z "$PY" ]; then
        # torch 2.13.0 (CPU build) is provided for Python 3.11 on this machine kind.
        for candidate in python3.11 python3; do
            if command -v "$candidate" >/dev/null 2>&1; then PY="$candidate"; break; fi
        done
    fi
    echo "pidlab setup: creating .venv with $($PY --version)"
    "$PY" -m venv .venv
fi

stamp=.venv/.pidlab-lock.sha256
want=$(cat requirements.lock pyproject.toml | sha256sum | cut -d' ' -f1)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
    echo "pidlab setup: installing the locked dependencies (CPU build of torch)"
    .venv/bin/python -m pip install --quiet --disable-pip-version-check -r requirements.lock
    .venv/bin/python -m pip install --quiet --disable-pip-version-check --no-deps --no-build-isolation -e . \
        || .venv/bin/python -m pip install --quiet --disable-pip-version-check --no-deps -e .
    echo "$want" > "$stamp"
fi
