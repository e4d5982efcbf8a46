#!/usr/bin/env bash
# The sixteenth session's GPU job (issues 14 and 13) on one machine of several GPUs (nvidia-h100-x4:
# 4 GPUs, 64 cores): Stage 2 on all training pairs and the collision estimators on all training
# pairs, side by side, each on GPUs of its own, resuming across warm calls.
#
#   bash scripts/device_slim.sh out
#   run(kind="nvidia-h100-x4", carry=[".whl_min", ".whl_train"], timeout_s=600,
#       command="bash scripts/device_multi.sh train")        # call 1, then the same again (resumes)
#   bash scripts/device_slim.sh in
#
# train (each part a scripts/chain/ part, all under END_S):
#   GPU 0  Stage 2b fine-tuned from weights/where_small_paper on every training pair
#          (scripts/chain/stage2.sh: full derive on S2_W workers, pack, train_where; S2_ENV more
#          variables for it, e.g. "LR=1e-4")  -> $OUT/stage2.tgz (+ stage2_ckpt.tgz)
#   GPU 3  Stage 2 from scratch (2a, then 2b) on the same pack (RUN=scratch WAIT_PACK=1
#          SCRATCH=1; NO_SCRATCH=1 skips it)  -> $OUT/stage2_scratch.tgz (+ _ckpt)
#   GPU 1  the NCE (scripts/chain/nce.sh, NCE_W derive workers; BASE_ARGS, default: the support
#          crop with planner labels, a near-contact share of every batch, a cosine schedule and
#          a validation curve)
#   GPU 2  the control NCE beside it (CROP_ARGS: the support crop with the old settings) -> both in
#          $OUT/nce.tgz
# A machine with fewer GPUs runs the parts on GPU k mod (its count).
set -uo pipefail
CALL=${1:?usage: device_multi.sh train}
C=/tmp/chain
END_S=${END_S:-570}
LOG=multi.log
. scripts/device_preamble.sh
NG=$(nvidia-smi -L 2>/dev/null | grep -c '^GPU')
[ "${NG:-0}" -ge 1 ] || NG=1
gpu() { echo $(($1 % NG)); }
CORES=$(nproc)
S2_W=${S2_W:-$((CORES * 5 / 8))}
NCE_W=${NCE_W:-$((CORES * 5 / 16))}
BUDGET=$(($(left) - 10))
log "$NG GPUs, $CORES cores; budget $BUDGET s; Stage-2 derive $S2_W workers, NCE derive $NCE_W"

if [ "$CALL" = train ]; then
    NEW_NCE="--support-crop-from 2048 --planner-labels 1 --near-share 0.3 --lr-schedule cosine --val-curve-every 2000"
    # the first call trains at the default lr; a resumed call warm-restarts the cosine lower
    [ -f "$C/nce/run/nce/config.json" ] && NEW_NCE="$NEW_NCE --lr ${NCE_LR2:-5e-4}"
    env CUDA_VISIBLE_DEVICES="$(gpu 0)" CHAIN_WORKERS="$S2_W" XLA_PYTHON_CLIENT_MEM_FRACTION=0.8 \
        ${S2_ENV:-} bash scripts/chain/stage2.sh "$BUDGET" "$OUT" >>"$C/logs/stage2_part.log" 2>&1 &
    P_S2=$!
    P_SCRATCH=
    if [ -z "${NO_SCRATCH:-}" ]; then
        env CUDA_VISIBLE_DEVICES="$(gpu 3)" CHAIN_WORKERS=8 XLA_PYTHON_CLIENT_MEM_FRACTION=0.8 \
            RUN=scratch TGZ=stage2_scratch WAIT_PACK=1 SCRATCH=1 SCRATCH_2A=${SCRATCH_2A:-0.8} \
            bash scripts/chain/stage2.sh "$BUDGET" "$OUT" >>"$C/logs/stage2_scratch_part.log" 2>&1 &
        P_SCRATCH=$!
    fi
    env CUDA_VISIBLE_DEVICES="$(gpu 1)" CROP_GPU="$(gpu 2)" CHAIN_WORKERS="$NCE_W" \
        XLA_PYTHON_CLIENT_MEM_FRACTION=0.4 BASE_ARGS="${BASE_ARGS:-$NEW_NCE}" \
        CROP_ARGS="${CROP_ARGS:---val-curve-every 2000}" \
        bash scripts/chain/nce.sh "$BUDGET" "$OUT/nce.tgz" >>"$C/logs/nce_part.log" 2>&1 &
    P_NCE=$!
    wait "$P_S2"
    log "Stage 2 (fine-tune): exit $? | $(grep -h '\] ' "$C"/s2/logs/call_run_*.log 2>/dev/null | tail -4 | tr '\n' ' ' | cut -c1-700)"
    if [ -n "$P_SCRATCH" ]; then
        wait "$P_SCRATCH"
        log "Stage 2 (scratch): exit $? | $(grep -h '\] ' "$C"/s2/logs/call_scratch_*.log 2>/dev/null | tail -3 | tr '\n' ' ' | cut -c1-500)"
    fi
    wait "$P_NCE"
    log "NCE: exit $? | $(tail -6 "$C/nce/logs/call_$(ls "$C/nce/logs" | grep -c '^call_').log" 2>/dev/null | tr '\n' ' ' | cut -c1-900)"
    (cd "$C" && tar -czf "$OUT/multi_logs.tgz" logs s2/logs nce/logs 2>/dev/null)
    ls -la "$OUT" | tee -a "$OUT/$LOG"
    log "done"
    exit 0
fi
log "unknown call $CALL"
exit 2
