#!/usr/bin/env bash
# The eighteenth session's GPU job for issue 13 on ONE GPU (16 cores): two NCEs trained side by
# side by scripts/chain/nce.sh on every training pair derived so far, resuming across warm calls
# of the same machine (state in /tmp/chain/nce/; a fresh machine starts over).
#
#   bash scripts/device_slim.sh out
#   run(carry=[".whl_min", ".whl_train"], timeout_s=600, command="bash scripts/device_nce.sh")
#   ... the same again (resumes: more pairs derived, both NCEs trained on)
#   bash scripts/device_slim.sh in
#
# base slot  (weights/):      BASE_PRESET (contact: the contact NCE, NCEConfig.local_points)
# crop slot  (weights_crop/): CROP_PRESET (small: 512 + 512 points, the support crop from 2,048)
# Both with the sixteenth session's planner options (planner labels, a near-contact share of
# 0.3, cosine lr restarted at NCE_LR2 on a resumed call, a validation curve every 2,000 steps);
# no HCE normal net (NORMALS_S=0). Output: $OUT/nce.tgz (weights, weights_crop, logs,
# summary.json), $OUT/nce.log.
set -uo pipefail
CALL=nce
C=/tmp/chain
END_S=${END_S:-580}
LOG=nce.log
. scripts/device_preamble.sh
# SEED_FROM=weights/<folder> (twenty-third session): both slots start from that NCE (its nce/
# and nce_history.jsonl copied in) on a fresh machine: a fine-tune, resumed like a later call
if [ -n "${SEED_FROM:-}" ] && [ ! -f "$C/nce/run/nce/config.json" ]; then
    for d in run run_crop; do
        mkdir -p "$C/nce/$d" && cp -r "$SEED_FROM/nce" "$SEED_FROM/nce_history.jsonl" "$C/nce/$d/"
    done
    log "both slots seeded from $SEED_FROM"
fi
# PAIRS_IN=<folder of derived training-pair files> (twenty-ninth session): copied into the
# derive's folder first, so that those pairs (e.g. the ones eval_paths --mine planned on, whose
# mined states BASE_EXTRA / CROP_EXTRA="--mined DIR --mined-share S" train on) are there
# whatever the derive reaches in the call
if [ -n "${PAIRS_IN:-}" ]; then
    mkdir -p "$C/nce/derived/train"
    cp -n "$PAIRS_IN"/*.npz "$C/nce/derived/train/" 2>/dev/null
    log "copied $(ls "$PAIRS_IN" | wc -l) derived training pairs from $PAIRS_IN"
fi
NEW="--planner-labels 1 --near-share 0.3 --lr-schedule cosine --val-curve-every 2000"
[ -f "$C/nce/run/nce/config.json" ] && NEW="$NEW --lr ${NCE_LR2:-5e-4}"
log "derived so far: $(ls $C/nce/derived/train 2>/dev/null | wc -l) training pairs"
env PYTHON="$PY" CHAIN_WORKERS="${NCE_W:-13}" PRESET="${BASE_PRESET:-contact}" NORMALS_S=0 \
    XLA_PYTHON_CLIENT_MEM_FRACTION="${MEM_FRACTION:-0.4}" BASE_ARGS="$NEW ${BASE_EXTRA:-}" \
    CROP_ARGS="--preset ${CROP_PRESET:-small} $NEW ${CROP_EXTRA:-}" \
    DERIVE_FRACTION="${DERIVE_FRACTION:-0.4}" bash scripts/chain/nce.sh $(($(left) - 10)) "$OUT/nce.tgz" \
    >>"$C/logs/nce_part.log" 2>&1
log "nce.sh exit $? | $(tail -8 "$C/nce/logs/call_$(ls "$C/nce/logs" | grep -c '^call_').log" 2>/dev/null | tr '\n' ' ' | cut -c1-1500)"
ls -la "$OUT" | tee -a "$OUT/$LOG"
