#!/usr/bin/env bash
# The any-frame figures in one device call: the object-frame network trained in the background
# (scripts/device_frame.sh, 4 render cores) while `experiments.evaluate where` measures the default
# answer on the first PAIRS held-out pairs in the any-frame protocol and in the library's frame;
# then the freshly trained network goes into weights/frame (on the machine) and the `any_frame`
# answer is measured on the same pairs in both frames. Seed 0 throughout.
#
#   bash scripts/device_lean.sh out where
#   run(carry=[".whl_min", ".whl_train"], timeout_s=600, command="bash scripts/device_anyframe.sh")
#   bash scripts/device_lean.sh back
#
# PAIRS (default 400), FRAME_S (training seconds, default 250), FRAME_STEPS (default 8000), TOTAL_S
# (the call's seconds, default 585).
# Back in $OUT: frame/ (history.jsonl, best/: copy to weights/frame), evaluate.log,
# where_results.json (keys default, default_any_frame, any_frame, any_frame_any_frame) and the
# per-pair records.
set -uo pipefail
OUT=${OUT:-/tmp/out}
PAIRS=${PAIRS:-400}
t0=$(date +%s)
FRAME_WORKERS=4 FRAME_VIEWS=24 FRAME_CAMERA=0.5 FRAME_STEPS=${FRAME_STEPS:-8000} FRAME_BATCH=64 \
    FRAME_S=${FRAME_S:-250} END_S=$((${FRAME_S:-250} + 120)) OUT=$OUT bash scripts/device_frame.sh \
    >"$OUT/frame_call.txt" 2>&1 &
frame_pid=$!
sleep 20  # the frame call installs the carried wheels first
ev() { SEEDS=0 BATCH=4 EVAL_WORKERS=12 PAIRS=$PAIRS MODE=where bash scripts/device_evaluate.sh; }
END_S=170 DERIVE_S=90 FRAME=any CONFIG=default ev
END_S=90 CONFIG=default ev
wait $frame_pid
echo "[$(($(date +%s) - t0)) s] frame call done: $(tail -n 1 "$OUT/frame_call.txt")" | tee -a "$OUT/evaluate.log"
if [ -s "$OUT/frame/best/params.msgpack" ]; then
    cp "$OUT/frame/best/config.json" "$OUT/frame/best/params.msgpack" weights/frame/
    left=$((${TOTAL_S:-585} - $(date +%s) + t0))
    END_S=$((left / 2)) FRAME=any CONFIG=any_frame ev
    left=$((${TOTAL_S:-585} - $(date +%s) + t0))
    END_S=$((left - 5)) CONFIG=any_frame ev
else
    echo "no trained frame network: any_frame not measured" | tee -a "$OUT/evaluate.log"
fi
