#!/usr/bin/env bash
# Issue 12 (forty-seventh session): rankers fine-tuned on the DEFAULT pipeline's own answer pools
# (three views x K = 10 x two starts = 60 candidates a pair) of training pairs, on one GPU.
#
#   MORE=1 STAGE3=1 POOLS=1 bash scripts/device_slim.sh out      # (+ POOLS_WEIGHTS=... for train/score)
#   run(carry=[".whl_min", ".whl_train", "out/s47/in"], command="bash scripts/device_pools.sh records")
#   run(..., command="bash scripts/device_pools.sh train")    # warm: the records stay on the machine
#   run(carry=[..., "out/s47/keys"], command="bash scripts/device_pools.sh score")   # warm
#   (a fresh machine for train: the records made slim on the VM, carried as POOL_IN; train then
#   score in one call, as the forty-seventh session's calls 2 and 3 did)
#   bash scripts/device_slim.sh in
#
# CALL
#   records  the pairs of POOL_PAIRS (results/ranker_pairs_f.jsonl; derived, full recipe) through
#            eval_stage3 --proposals 10 once per view of POOL_VIEWS ("0/1 1/2 3/4": the default
#            pipeline's), each run as scripts/device_full.sh val (every candidate simulated with
#            the evaluation protocol); a view whose records are already on the machine is
#            skipped, and a view starts only with MIN_VIEW_S (190 s) left. Records back in $OUT
#            (val_POOL_NAME_vJofT.pairs.jsonl.gz) and kept in /tmp/full/records.
#   train    records for the views still missing (if the time allows; POOL_IN: a folder of slim
#            tables NAME_vJofT.npz carried from an earlier machine's records), then every view's records
#            made slim and joined into one pool a pair (train_ranker union ->
#            $OUT/rank_POOL_NAME.npz), then scripts/device_ranker.sh train on it with
#            RANK_VARIANTS (e.g. "f20=--init=weights/value_s20_ranker,--steps=1200"); the
#            validation curve's table comes from RANK_IN_EXTRA (out/s47/in: val_*.npz).
#   score    every trained ranker (/tmp/full/ranker/NAME/value, or RANKERS="NAME ...") on the
#            carried key tables (KEYS_IN, out/s47/keys: experiments.rank_views pack's val*.npz
#            and held*.npz) as the pipeline would score them -> $OUT/NAME_KEY.npy; derives the
#            held-out pairs first if absent (the validation pairs: by the train call before it).
set -uo pipefail
CALL=${1:?usage: device_pools.sh records|train|score}
C=/tmp/full
END_S=${END_S:-585}
LOG=pools.log
. scripts/device_preamble.sh
NAME=${POOL_NAME:-pool_f}
PAIRS=${POOL_PAIRS:-results/ranker_pairs_f.jsonl}
tag_of() { echo "v$(echo "$1" | sed 's|0/1|0|; s|/|of|')"; }  # 0/1 -> v0, 1/2 -> v1of2
derive_test() {  # WORKERS: the held-out pairs a score call reads, unless already derived
    [ "$(ls "$C/ds/derived/test" 2>/dev/null | wc -l)" -ge 1794 ] && return 0
    timeout -k 5 $(($(left) - 20)) $PY -m experiments.derive_dataset --data "$C/ds" --split test \
        --workers "$1" --pairs-from results/heldout_pairs.jsonl --no-progress >>"$C/logs/derive_test.log" 2>&1
    log "held-out pairs derived: $(ls "$C/ds/derived/test" | wc -l)"
}

records() {
    for v in ${POOL_VIEWS:-0/1 1/2 3/4}; do
        local t
        t=$(tag_of "$v")
        [ -e "$C/records/val_${NAME}_$t.pairs.jsonl.gz" ] && { log "view $v: records there"; continue; }
        [ "$(left)" -ge "${MIN_VIEW_S:-190}" ] || { log "view $v: $(left) s left, not started"; continue; }
        log "view $v: eval_stage3 on $PAIRS"
        OUT=$OUT VAL_PAIRS=$PAIRS VAL_NAME="${NAME}_$t" VAL_ARGS="--proposals 10 --view $v" \
            END_S=$(($(left) - 5)) bash scripts/device_full.sh val >/dev/null 2>&1
        if [ -e "$C/records/val_${NAME}_$t.pairs.jsonl.gz" ]; then
            log "view $v: $($PY -c "import json; d = json.load(open('$OUT/val_${NAME}_$t.json')); print({k: round(x['mean'], 2) for k, x in d.items() if isinstance(x, dict) and 'mean' in x})" 2>&1 | tail -c 300)"
        else
            log "view $v: no records (see full.log)"
        fi
    done
}

if [ "$CALL" = records ]; then
    records
    log "done"
    exit 0
fi

if [ "$CALL" = train ]; then
    P=$C/pools
    mkdir -p "$P/in"
    # POOL_IN: slim tables of views recorded on an earlier machine (NAME_vJofT.npz, carried)
    [ -n "${POOL_IN:-}" ] && cp "$POOL_IN"/*.npz "$P/" 2>/dev/null
    for v in ${POOL_VIEWS:-0/1 1/2 3/4}; do
        [ -e "$P/${NAME}_$(tag_of "$v").npz" ] || { records; break; }
    done
    tables=
    for v in ${POOL_VIEWS:-0/1 1/2 3/4}; do
        t=$(tag_of "$v")
        rec=$C/records/val_${NAME}_$t.pairs.jsonl.gz
        [ -e "$rec" ] || [ -e "$P/${NAME}_$t.npz" ] || { log "error: no records of view $v"; exit 3; }
        [ -e "$P/${NAME}_$t.npz" ] || $PY -m experiments.train_ranker slim "$rec" "$P/${NAME}_$t.npz" >>"$C/logs/pools_slim.log" 2>&1
        tables="$tables $P/${NAME}_$t.npz"
    done
    # the held-out pairs for a score call on this machine, derived on the CPU while the GPU trains
    if ls "${KEYS_IN:-out/s47/keys}"/held*.npz >/dev/null 2>&1; then
        derive_test 8 &
        DTEST=$!
    fi
    $PY -m experiments.train_ranker union $tables "$P/in/rank_$NAME.npz" 2>&1 | tee -a "$OUT/$LOG"
    cp "$P/in/rank_$NAME.npz" "$OUT/"
    RANK_IN="$P/in ${RANK_IN_EXTRA:-out/s47/in}" END_S=$(($(left) - 5)) \
        RANK_TRAIN_BUDGET=$(($(left) - 45)) bash scripts/device_ranker.sh train >/dev/null 2>&1
    cat "$OUT/ranker.log" >>"$OUT/$LOG" 2>/dev/null
    [ -n "${DTEST:-}" ] && wait "$DTEST"
    log "done"
    exit 0
fi

if [ "$CALL" = score ]; then
    K=${KEYS_IN:-out/s47/keys}
    ls "$K"/held*.npz >/dev/null 2>&1 && derive_test 16
    for name in ${RANKERS:-$(ls "$C/ranker" 2>/dev/null)}; do
        [ -d "$C/ranker/$name/value" ] || continue
        for split in val held; do
            ls "$K"/$split*.npz >/dev/null 2>&1 || continue
            clouds=$C/ds/derived/$([ $split = val ] && echo train || echo test)
            [ "$(left)" -gt 30 ] || { log "no time left for $name $split"; continue; }
            timeout $(($(left) - 10)) $PY -m experiments.rank_views score --ranker "$C/ranker/$name/value" \
                --name "$name" --table "$K"/$split*.npz --clouds "$clouds" --out "$OUT" 2>&1 |
                grep -v '^view' | tail -4 | tee -a "$OUT/$LOG"
        done
    done
    log "done"
    exit 0
fi
echo "unknown call $CALL" >&2
exit 2
