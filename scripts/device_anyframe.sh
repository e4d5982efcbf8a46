#!/usr/bin/env bash
# The any-frame figures in one device call: `experiments.evaluate where` on the first PAIRS
# held-out pairs (seed 0) for each "CONFIG FRAME" of RUNS, in order, each stopping itself so
# that the later ones get their share of the call:
#   default any     the default answer with the object in a random frame (the baseline)
#   frames any      where.FRAMES (32 frame hypotheses for Stages 1-2, V picks the starts)
#   frames library  where.FRAMES on the clouds as derived (the canonical figure it would give)
#
#   bash scripts/device_lean.sh out where
#   run(carry=[".whl_min", ".whl_train"], timeout_s=600, command="bash scripts/device_anyframe.sh")
#   bash scripts/device_lean.sh back
#
# PAIRS (default 400), RUNS (default the four above, "CONFIG:FRAME" words), TOTAL_S (the call's
# seconds, default 585). Back in $OUT: evaluate.log, where_results.json (keys default_any_frame,
# frames_any_frame, frames) and the per-pair records.
set -uo pipefail
OUT=${OUT:-/tmp/out}
PAIRS=${PAIRS:-400}
RUNS=${RUNS:-default:any frames:any frames:library}
t0=$(date +%s)
# where.FRAMES's Stage 1 (weights/stage1_frames): the tree's, else what a warm machine's
# `STAGE=1 ... scripts/device_train.sh` call left in /tmp/export
if [ ! -s weights/stage1_frames/stage1/params.msgpack ] && [ -s /tmp/export/stage1/params.msgpack ]; then
    mkdir -p weights/stage1_frames && cp -r /tmp/export/stage1 weights/stage1_frames/
    echo "weights/stage1_frames from /tmp/export (the training call on this machine)"
fi
# where.CANON's object-frame network (weights/canon) likewise
if [ ! -s weights/canon/stagecanon/params.msgpack ] && [ -s /tmp/export/stagecanon/params.msgpack ]; then
    mkdir -p weights/canon && cp -r /tmp/export/stagecanon weights/canon/
    echo "weights/canon from /tmp/export (the training call on this machine)"
fi
set -- $RUNS
n=$#
for run in "$@"; do
    left=$((${TOTAL_S:-585} - $(date +%s) + t0))
    share=$((left / n))
    n=$((n - 1))
    SEEDS=0 BATCH=4 PAIRS=$PAIRS MODE=where CONFIG=${run%%:*} FRAME=${run##*:} END_S=$share \
        DERIVE_S=90 bash scripts/device_evaluate.sh
done
