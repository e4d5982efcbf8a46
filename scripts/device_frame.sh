#!/usr/bin/env bash
# The object-frame network (experiments.train_frame, weights/frame) on the device: partial clouds
# of every training object rendered on FRAME_WORKERS CPU cores (default 4: it can run beside
# scripts/device_evaluate.sh), then training on the GPU for at most FRAME_S seconds (default
# END_S - 60), resumable on the machine ($C/frame) or from a carried run folder (FRAME_IN).
#
#   run(carry=[".whl_min", ".whl_train"], command="bash scripts/device_frame.sh")
#
# FRAME_STEPS (default 12000), FRAME_BATCH (64), FRAME_VIEWS (32), FRAME_CAMERA (the camera's
# resolution scale, 1.0). Back in $OUT/frame:
# history.jsonl, run.json, best/ (config.json + params.msgpack: copy to weights/frame),
# checkpoint.msgpack (to resume elsewhere) and frame.log.
set -uo pipefail
CALL=frame
C=${C:-/tmp/frame}
END_S=${END_S:-560}
LOG=frame.log
OUT=${OUT:-/tmp/out}/frame
. scripts/device_preamble.sh
export JAX_COMPILATION_CACHE_DIR=$C/jax_cache
mkdir -p "$C/run"
cp datasets/paper/dataset_card.json "$C/ds/"
[ -n "${FRAME_IN:-}" ] && [ ! -s "$C/run/checkpoint.msgpack" ] && cp -r "$FRAME_IN"/. "$C/run/"
t=$(date +%s)
$PY -m experiments.train_frame render --data "$C/ds" --views "${FRAME_VIEWS:-32}" --camera-scale "${FRAME_CAMERA:-1.0}" \
    --workers "${FRAME_WORKERS:-4}" --out "$C/clouds.npz" >"$C/logs/render.log" 2>&1
log "render: rc $? after $(($(date +%s) - t)) s; $(tail -n 1 "$C/logs/render.log")"
t=$(date +%s)
$PY -m experiments.train_frame train --clouds "$C/clouds.npz" --steps "${FRAME_STEPS:-12000}" \
    --batch "${FRAME_BATCH:-64}" --max-seconds "${FRAME_S:-$(($(left) - 60))}" --out "$C/run" \
    >"$C/logs/train.log" 2>&1
log "train: rc $? after $(($(date +%s) - t)) s"
grep -v "^{" "$C/logs/train.log" | tail -n 5 >>"$OUT/$LOG"
tail -n 2 "$C/run/history.jsonl" >>"$OUT/$LOG"
cp -r "$C/run/history.jsonl" "$C/run/run.json" "$C/run/checkpoint.msgpack" "$C/run/best" "$OUT/" 2>/dev/null
log "done; back in \$OUT/frame: $(ls "$OUT" | tr '\n' ' ')"
