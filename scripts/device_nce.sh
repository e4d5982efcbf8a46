#!/usr/bin/env bash
# The NCE's GPU job on ONE GPU (16 cores): the contact NCE and the HCE normal net trained by
# scripts/chain/nce.sh on every training pair derived so far, resuming across warm calls of the
# same machine (state in /tmp/chain/nce/; a fresh machine starts over). weights/nce is its
# output.
#
#   run(carry=[".whl_min", ".whl_train"], timeout_s=600, command="bash scripts/device_nce.sh")
#   ... the same again (resumes: more pairs derived, the NCE trained on)
#
# train_collision's defaults (preset contact, planner labels, stable and far free poses, a
# near-contact share of 0.3, cosine lr), the cosine restarted at NCE_LR2 on a resumed call,
# a validation curve every 2,000 steps. Output: $OUT/nce.tgz (weights, logs, summary.json),
# $OUT/nce.log.
set -uo pipefail
CALL=nce
C=/tmp/chain
END_S=${END_S:-580}
LOG=nce.log
. scripts/device_preamble.sh
# SEED_FROM=weights/<folder>: start from that NCE (its nce/ and nce_history.jsonl copied in) on a
# fresh machine: a fine-tune, resumed like a later call
if [ -n "${SEED_FROM:-}" ] && [ ! -f "$C/nce/run/nce/config.json" ]; then
    mkdir -p "$C/nce/run" && cp -r "$SEED_FROM/nce" "$SEED_FROM/nce_history.jsonl" "$C/nce/run/"
    log "seeded from $SEED_FROM"
fi
NEW="--val-curve-every 2000"
[ -f "$C/nce/run/nce/config.json" ] && NEW="$NEW --lr ${NCE_LR2:-5e-4}"
log "derived so far: $(ls $C/nce/derived/train 2>/dev/null | wc -l) training pairs"
env PYTHON="$PY" CHAIN_WORKERS="${NCE_W:-13}" PRESET="${PRESET:-contact}" \
    XLA_PYTHON_CLIENT_MEM_FRACTION="${MEM_FRACTION:-0.4}" BASE_ARGS="$NEW ${EXTRA:-}" \
    DERIVE_FRACTION="${DERIVE_FRACTION:-0.4}" bash scripts/chain/nce.sh $(($(left) - 10)) "$OUT/nce.tgz" \
    >>"$C/logs/nce_part.log" 2>&1
log "nce.sh exit $? | $(tail -8 "$C/nce/logs/call_$(ls "$C/nce/logs" | grep -c '^call_').log" 2>/dev/null | tr '\n' ' ' | cut -c1-1500)"
ls -la "$OUT" | tee -a "$OUT/$LOG"
