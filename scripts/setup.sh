#!/usr/bin/env bash
# Create .venv (if missing) and install the project with its test tools.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ ! -x .venv/bin/python ]; then
  python3 -m venv .venv
fi
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e ".[dev,bench]"  # bench: PyBullet, the second judge
# Headless Chromium (Debian's `chromium`) for the test of experiments.hang's viewer.html.
# Installed with apt-get when we are root (or have password-less sudo); otherwise, or with
# OMNIHANG_NO_CHROMIUM=1, that one test skips and says why.
if ! command -v chromium >/dev/null && [ -z "${OMNIHANG_NO_CHROMIUM:-}" ] && command -v apt-get >/dev/null; then
  SUDO=""
  if [ "$(id -u)" != 0 ]; then SUDO="sudo -n"; fi
  if [ -z "$SUDO" ] || sudo -n true 2>/dev/null; then
    echo "installing chromium (apt-get) for the viewer-page test"
    export DEBIAN_FRONTEND=noninteractive
    $SUDO apt-get install -y -q chromium >/dev/null 2>&1 \
      || { $SUDO apt-get update -q >/dev/null 2>&1 && $SUDO apt-get install -y -q chromium >/dev/null 2>&1; } \
      || echo "could not install chromium: the viewer-page test will skip"
  fi
fi
