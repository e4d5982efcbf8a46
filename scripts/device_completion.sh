#!/usr/bin/env bash
# Twenty-fifth session, issue 13: train the shape-completion networks (object and support,
# omnihang_jax.completion) on ONE GPU; its 16 cores render the views (experiments.train_completion).
# Resumes on a warm machine (state in /tmp/chain/completion/; a fresh machine starts over).
#
#   bash scripts/device_slim.sh out
#   run(carry=[".whl_min", ".whl_train"], timeout_s=600, command="bash scripts/device_completion.sh")
#   bash scripts/device_slim.sh in
#
# Output: $OUT/completion.tgz (the two networks' folders without their checkpoints, metrics.json),
# $OUT/completion.log. STEPS / BATCH / EXTRA pass through.
set -uo pipefail
CALL=completion
C=/tmp/chain
END_S=${END_S:-580}
LOG=completion.log
. scripts/device_preamble.sh
mkdir -p "$C/completion"
timeout $(($(left) - 25)) $PY -m experiments.train_completion --data "$C/ds" --out "$C/completion/run" \
    --steps "${STEPS:-30000}" --batch "${BATCH:-64}" --workers "${WORKERS:-15}" --no-progress ${EXTRA:-} \
    >>"$OUT/$LOG" 2>&1
log "train_completion exit $?"
tar czf "$OUT/completion.tgz" --exclude checkpoint.msgpack -C "$C/completion" run
ls -la "$OUT" | tee -a "$OUT/$LOG"
