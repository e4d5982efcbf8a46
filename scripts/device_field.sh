#!/usr/bin/env bash
# Forty-ninth session, issue 12: train the object's distance field (omnihang_jax.distance_field,
# experiments.train_distance_field) on ONE GPU (its 16 cores render the views), then, with
# EXTRACT=1, the field's points for the probe pairs (scripts/field_points.py extract; the inputs
# out/s49/probe_inputs.npz travel in carry). Resumes on a warm machine (state in /tmp/chain/field/;
# a fresh machine renders and starts over).
#
#   python scripts/field_points.py pack --out out/s49/probe_inputs.npz
#   bash scripts/device_slim.sh out
#   run(carry=[".whl_min", ".whl_train", "out/s49/probe_inputs.npz"], timeout_s=600,
#       command="STEPS=30000 bash scripts/device_field.sh")
#   bash scripts/device_slim.sh in
#
# Output: $OUT/field.tgz (the run folder with its resumable checkpoint, ~3 MB), $OUT/field.log,
# with EXTRACT=1 $OUT/field_points.partNN.npz. STEPS / BATCH / EXTRA / RESERVE pass through.
# FIELD=weights/field_s49 skips the training and extracts with that field; VARIANTS="NAME:ARGS;..."
# extracts once per variant (ARGS passed to field_points.py extract), $OUT/NAME.partNN.npz each.
# RESUME=dir (a run folder brought back from an earlier call, in the tree or carry) continues that
# run on a fresh machine: a lost warm machine no longer loses the training (fiftieth session).
set -uo pipefail
CALL=field
C=/tmp/chain
END_S=${END_S:-585}
LOG=field.log
. scripts/device_preamble.sh
mkdir -p "$C/field"
if [ -n "${RESUME:-}" ] && [ ! -e "$C/field/run" ]; then
    cp -r "$RESUME" "$C/field/run" && log "resuming from $RESUME ($(wc -l <"$RESUME/history.jsonl") evaluations)"
fi
if [ -n "${FIELD:-}" ]; then
    IFS=';' read -ra VS <<<"${VARIANTS:-field_points:}"
    for v in "${VS[@]}"; do
        timeout $(($(left) - 8)) $PY scripts/field_points.py extract --field "$FIELD" \
            --inputs out/s49/probe_inputs.npz --out "$OUT/${v%%:*}" --no-progress ${v#*:} >>"$OUT/$LOG" 2>&1
        log "field_points ${v%%:*} exit $?"
    done
    ls -la "$OUT" | tee -a "$OUT/$LOG"
    exit 0
fi
timeout $(($(left) - ${RESERVE:-20})) $PY -m experiments.train_distance_field --data "$C/ds" \
    --out "$C/field/run" --steps "${STEPS:-30000}" --batch "${BATCH:-32}" --workers "${WORKERS:-15}" \
    --no-progress ${EXTRA:-} >>"$OUT/$LOG" 2>&1
log "train_distance_field exit $?"
tail -n 3 "$C/field/run/history.jsonl" | tee -a "$OUT/$LOG"
if [ -n "${EXTRACT:-}" ]; then
    timeout $(($(left) - 8)) $PY scripts/field_points.py extract --field "$C/field/run" \
        --inputs out/s49/probe_inputs.npz --out "$OUT/field_points" --no-progress >>"$OUT/$LOG" 2>&1
    log "field_points exit $?"
fi
tar czf "$OUT/field.tgz" -C "$C/field" run
ls -la "$OUT" | tee -a "$OUT/$LOG"
