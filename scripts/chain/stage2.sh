#!/usr/bin/env bash
# Chain part "stage2" (issue 14; docs/networks.md "Stage 2 on all training pairs"): Stage 2
# (2a contact scores + 2b correspondences, one network: 2b fine-tunes the 2a features with the
# 2a term in its loss) fine-tuned from the committed weights on every training pair, resuming
# across calls of the same machine.
#
#   bash scripts/chain/stage2.sh BUDGET_S OUT_DIR        # e.g. 560 $OUT
#   SKIP_INSTALL=1 CHAIN_TINY=1 bash scripts/chain/stage2.sh 150 /tmp/s2out   # local test
#
# One call (all under BUDGET_S wall clock):
# 1. derive (CPU, CHAIN_WORKERS processes, resumable) the FULL pair files of the training split
#    (clouds + contact maps: Stage 2's input; `derive_dataset`, the recipe's 640 x 480 camera)
#    until DERIVE_FRACTION of the budget (first call) or until all are there;
# 2. pack them (`pack_dataset`; again on a later call when more pairs were derived);
# 3. train Stage 2b on the GPU (`train_where --stage 2b --preset small`) from INIT (the
#    committed weights/where_small_paper), batch BATCH (128), lr LR (3e-4) with warm-up 300
#    and cosine over STEPS (35000) total steps (a later call resumes the schedule), validation
#    every 500 steps on the fixed 10 % of training objects (never trained on), best kept;
# 4. export best and latest (Stage 2b + INIT's Stage 1: a complete weights folder) into
#    OUT_DIR/stage2.tgz with the metrics, validation curve and logs; the resumable checkpoint
#    (params + Adam state) into OUT_DIR/stage2_ckpt.tgz.
# Knobs (env): CHAIN_DS (/tmp/chain/ds: recipe.json + shards/), STAGE2_STATE (/tmp/chain/s2),
# CHAIN_WORKERS (16), DERIVE_FRACTION (0.55), N_TRAIN (0 = all), INIT, BATCH, LR, STEPS,
# TRAIN_RESERVE_S (60: export + tarballs after training), GPU memory:
# XLA_PYTHON_CLIENT_MEM_FRACTION (0.45 unless set).
# CHAIN_TINY=1: tiny dataset (the local test): N_TRAIN 24, batch 4, 30 steps.
# A variant beside the main run (another GPU, the same pack): RUN (run folder name, "run"),
# WAIT_PACK=1 (no derive or pack of its own: wait until the main run's pack exists),
# SCRATCH=1 (2a from scratch, then 2b from it: `--stage 2`, no INIT; SCRATCH_2A share of the
# training time for 2a, 0.4), TGZ (tarball name, "stage2").
set -uo pipefail
BUDGET=${1:?usage: stage2.sh BUDGET_S OUT_DIR}
OUTD=${2:?usage: stage2.sh BUDGET_S OUT_DIR}
T0=$(date +%s)
STATE=${STAGE2_STATE:-/tmp/chain/s2}
DS=${CHAIN_DS:-/tmp/chain/ds}
WORKERS=${CHAIN_WORKERS:-16}
INIT=${INIT:-weights/where_small_paper}
RUN=${RUN:-run}
TGZ=${TGZ:-stage2}
mkdir -p "$STATE/logs" "$OUTD"
CALL=$(($(ls "$STATE/logs" | grep -c "^call_${RUN}_") + 1))
LOG=$STATE/logs/call_${RUN}_$CALL.log
elapsed() { echo $(($(date +%s) - T0)); }
left() { echo $((BUDGET - $(elapsed))); }
log() { echo "[stage2 call $CALL, $(elapsed) s] $*" | tee -a "$LOG"; }
if [ -n "${CHAIN_TINY:-}" ]; then
    N_TRAIN=${N_TRAIN:-24} BATCH=${BATCH:-4} STEPS=${STEPS:-30} EVAL_EVERY=10 WARMUP=5
    TRAIN_RESERVE_S=${TRAIN_RESERVE_S:-25}
else
    N_TRAIN=${N_TRAIN:-0} BATCH=${BATCH:-128} STEPS=${STEPS:-35000} EVAL_EVERY=500 WARMUP=300
    TRAIN_RESERVE_S=${TRAIN_RESERVE_S:-60}
fi
LR=${LR:-3e-4}
DERIVE_FRACTION=${DERIVE_FRACTION:-0.55}
export PYTHONPATH=${PYTHONPATH:-/tmp/site:$PWD} PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
export XLA_PYTHON_CLIENT_MEM_FRACTION=${XLA_PYTHON_CLIENT_MEM_FRACTION:-0.45}
PY=${PYTHON:-python3}
if [ -n "${SKIP_INSTALL:-}" ] && [ -z "${PYTHON:-}" ] && [ -x .venv/bin/python ]; then PY=.venv/bin/python; fi
if [ ! -f "$DS/recipe.json" ]; then
    log "error: $DS/recipe.json missing (the chain's dataset)"
    exit 3
fi
n_train_pairs() { $PY -c "
import json; r = json.load(open('$DS/recipe.json'))
print(sum(1 for p in r['pairs'] if p[2] == 'train'))" 2>/dev/null || echo 0; }
n_derived() { ls "$DS/derived/train" 2>/dev/null | grep -c '\.npz$'; }
TOTAL=$(n_train_pairs)
[ "$N_TRAIN" -gt 0 ] && TOTAL=$N_TRAIN
log "budget $BUDGET s; $(n_derived) training pairs derived (of $TOTAL in the recipe; pairs without a stable pose are never derived); init $INIT; batch $BATCH, lr $LR, $STEPS steps"

# 1. derive (resumable: files already there are skipped)
DERIVE_END=$(awk "BEGIN {print int($BUDGET * $DERIVE_FRACTION)}")
if [ -n "${WAIT_PACK:-}" ]; then
    while [ ! -f "$STATE/pack/pack.json" ] && [ "$(left)" -gt $((TRAIN_RESERVE_S + 30)) ]; do sleep 5; done
    log "variant $RUN: pack $([ -f "$STATE/pack/pack.json" ] && echo found || echo missing)"
elif [ "$(n_derived)" -lt "$TOTAL" ]; then
    LIMIT=()
    [ "$N_TRAIN" -gt 0 ] && LIMIT=(--limit "$((N_TRAIN - $(n_derived)))")
    timeout -k 5 $((DERIVE_END - $(elapsed))) "$PY" -m experiments.derive_dataset --data "$DS" \
        --split train --workers "$WORKERS" "${LIMIT[@]}" --no-progress >>"$STATE/logs/derive_$CALL.log" 2>&1
    log "derive: exit $? ; $(n_derived) training pairs derived (of $TOTAL in the recipe; pairs without a stable pose are never derived)"
fi

# 2. pack (again when more pairs were derived than the pack holds)
PACKED=$(cat "$STATE/packed_count" 2>/dev/null || echo 0)
if [ -z "${WAIT_PACK:-}" ] && [ "$(n_derived)" -gt "$PACKED" ]; then
    N_NOW=$(n_derived)
    rm -rf "$STATE/pack_new"
    if "$PY" -m experiments.pack_dataset --data "$DS" --split train --out "$STATE/pack_new" \
        --threads "$WORKERS" --no-progress >"$STATE/logs/pack_$CALL.log" 2>&1; then
        rm -rf "$STATE/pack" && mv "$STATE/pack_new" "$STATE/pack" && echo "$N_NOW" >"$STATE/packed_count"
        log "packed $N_NOW pairs: $(tr -d '\n ' <"$STATE/logs/pack_$CALL.log" | cut -c1-160)"
    else
        log "error: pack failed (logs/pack_$CALL.log)"
    fi
fi
[ -f "$STATE/pack/pack.json" ] || { log "error: no pack"; exit 4; }

# 3. train 2b (resumes the checkpoint in $STATE/run; the schedule runs over STEPS in all)
TRAIN_S=$(($(left) - TRAIN_RESERVE_S))
STATUS=0
if [ "$TRAIN_S" -lt 10 ]; then
    log "no time left to train ($TRAIN_S s)"
else
    if [ -n "${SCRATCH:-}" ]; then
        S2A=$(awk "BEGIN {print int($TRAIN_S * ${SCRATCH_2A:-0.4})}")
        [ -f "$STATE/$RUN/stage2b/config.json" ] && S2A=0  # a later call: 2b only
        WHAT=(--stage 2 --time-budget "2a=$S2A,2b=$((TRAIN_S - S2A))")
    else
        WHAT=(--stage 2b --init-from "$INIT" --time-budget "2b=$TRAIN_S")
    fi
    log "training ${WHAT[*]} for $TRAIN_S s in $RUN (loading and compilation not counted by train_where)"
    timeout -k 5 $(($(left) - 15)) "$PY" -m experiments.train_where --data "$STATE/pack" \
        --out "$STATE/$RUN" --preset small "${WHAT[@]}" --batch "$BATCH" \
        --lr-stage2 "$LR" --warmup "$WARMUP" --steps "$STEPS" \
        --eval-every "$EVAL_EVERY" --checkpoint-every 1000 --no-progress \
        >>"$STATE/logs/train_${RUN}_$CALL.log" 2>&1
    STATUS=$?
    log "train_where: exit $STATUS; $(tail -1 "$STATE/logs/train_${RUN}_$CALL.log" | cut -c1-200)"
fi

# 4. export best + latest as complete weights folders, then the tarballs
"$PY" - "$STATE" "$RUN" "$INIT" >>"$LOG" 2>&1 <<'EOF'
import shutil, sys
from omnihang_jax import train
state, run, init = sys.argv[1:4]
for which in ("best", "latest"):
    dst = f"{state}/export_{run}/{which}"
    print(which, train.export_weights(f"{state}/{run}", dst, ("2b",), which=which))
    shutil.copytree(f"{init}/stage1", f"{dst}/stage1", dirs_exist_ok=True)
EOF
R=$RUN/stage2b
(cd "$STATE" && tar -czf "$OUTD/$TGZ.tgz" "export_$RUN" logs "$R/config.json" "$R/metrics.jsonl" \
    "$R/val_metrics.jsonl" "$R/throughput.json" "$R/loss.png" "$R/best/best.json" \
    "$RUN/stage2a/val_metrics.jsonl" "$RUN/stage2a/metrics.jsonl" "$RUN/stage2a/loss.png" 2>/dev/null)
(cd "$STATE" && tar -czf "$OUTD/${TGZ}_ckpt.tgz" "$R" 2>/dev/null)
log "wrote $OUTD/$TGZ.tgz ($(du -k "$OUTD/$TGZ.tgz" | cut -f1) KiB), ${TGZ}_ckpt.tgz ($(du -k "$OUTD/${TGZ}_ckpt.tgz" | cut -f1) KiB); status $STATUS"
exit "$STATUS"
