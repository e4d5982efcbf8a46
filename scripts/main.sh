#!/usr/bin/env bash
# Set up and run the main job on built-in defaults (asset + physics showcase).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
.venv/bin/python -m experiments.assets --out "${1:-out/assets}"
