#!/usr/bin/env bash
# The browser tests' system packages: Debian's chromium (driven by Playwright's Python package
# with executable_path=/usr/bin/chromium) and Mesa's EGL for MuJoCo's offscreen renderer.
# Idempotent: installs nothing when both are present.
set -euo pipefail
need=()
command -v chromium >/dev/null 2>&1 || need+=(chromium)
ldconfig -p 2>/dev/null | grep -q "libEGL_mesa.so.0" || need+=(libegl1 libegl-mesa0 libgl1-mesa-dri)
if [ "${#need[@]}" -gt 0 ]; then
    echo "pidlab test setup: installing ${need[*]} (Debian packages)"
    SUDO=""
    if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
fi
