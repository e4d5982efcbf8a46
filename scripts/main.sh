#!/usr/bin/env bash
# Set up and run the main job on built-in defaults:
#  1. the asset library + physics showcase (out/assets);
#  2. where to hang, end to end with the committed weights: derive a few held-out pairs of
#     the committed paper-dataset labels (partial clouds, contact maps), predict with the
#     trained Stage 1 + 2 networks, check every prediction in MuJoCo, draw the hangs
#     (out/where_demo/: results JSON, per-pair JSONL, hangs.png).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
OUT=${1:-out}
PAIRS=${PAIRS:-8}
.venv/bin/python -m experiments.assets --out "$OUT/assets"
.venv/bin/python -m experiments.derive_dataset --data datasets/paper --out "$OUT/where_demo/derived" \
    --split test --limit "$PAIRS" --workers 2
.venv/bin/python -m experiments.eval_where --model weights/where_small_paper \
    --data "$OUT/where_demo/derived" --limit "$PAIRS" --out "$OUT/where_demo/hanging_success.json" \
    --figure "$OUT/where_demo/hangs.png" --figure-pairs "$PAIRS" \
    --label "main job: committed weights on $PAIRS held-out pairs of the committed labels"
echo "main job done: $OUT/assets (library, hangs), $OUT/where_demo (predicted hangs)"
