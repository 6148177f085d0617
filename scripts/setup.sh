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
    # This machine kind's pip configuration names index folders that may not exist; pip warns
    # about each of them. Those lines are noise; everything else pip says is shown.
    quiet() { "$@" 2>&1 | { grep -v "is ignored: it is neither a file nor a directory" || true; }; return "${PIPESTATUS[0]}"; }
    quiet .venv/bin/python -m pip install --quiet --disable-pip-version-check -r requirements.lock
    quiet .venv/bin/python -m pip install --quiet --disable-pip-version-check --no-deps -e .
    echo "$want" > "$stamp"
fi
