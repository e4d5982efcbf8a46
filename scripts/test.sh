#!/usr/bin/env bash
# Set up, lint and run the default (fast) test suite. Extra args go to pytest.
# The suite runs in PYTEST_WORKERS (default 2) pytest-xdist processes: most of a test's time is
# XLA compilation on one core, so two workers on the 2-core CI machine take ~14.7 min where one
# took ~21 (thirty-third session). PYTEST_WORKERS=0 runs it in one process.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
.venv/bin/ruff check .
.venv/bin/ruff format --check .
.venv/bin/python -m pytest -q -n "${PYTEST_WORKERS:-2}" --durations=25 "$@"
