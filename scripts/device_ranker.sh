#!/usr/bin/env bash
# The answer's rankers (experiments.train_ranker, weights/rankers/) on one GPU.
#
#   # the per-pair records of an evaluation of the answer pipeline on training pairs, made slim
#   # locally: python -m experiments.train_ranker slim REC.pairs.jsonl.gz out/ranker/in/NAME.npz
#   run(carry=[".whl_min", ".whl_train", "out/ranker/in"], command="bash scripts/device_ranker.sh train")
#   run(carry=[..., "out/ranker/held"], command="bash scripts/device_ranker.sh score")  # same warm machine
#
# CALL
#   train  the records of a warm machine's val calls ($C/records/*.pairs.jsonl.gz, made slim)
#          and the carried slim tables (RANK_IN, default out/ranker/in and /held: rank_*.npz training,
#          val_*.npz validation objects, held_*.npz held-out runs); derives the training and
#          validation pairs (full recipe), then the held-out pairs in the background; trains
#          each of RANK_VARIANTS ("NAME=flags ...") side by side on the GPU for at most
#          END_S; back in $OUT: ranker_NAME.tgz (value/, metrics, curves, summary, log; one
#          file a variant, as the device returns at most 8 files a call).
#   score  every variant's ranker on the validation and held-out tables: the answer rule's
#          success with the run's V, the ranker alone and their mean log P(hang) ->
#          $OUT/score_{train,test}.json (+ .npz of the scores; train = the validation objects).
#   all    train, then score, in one call.
# RANK_TRAIN_BUDGET: the second of the call by which training ends (default END_S - 70; with
# `all`, leave the scoring ~25 s a variant).
set -uo pipefail
CALL=${1:?usage: device_ranker.sh train|score|all}
C=/tmp/full
END_S=${END_S:-580}
LOG=ranker.log
. scripts/device_preamble.sh
R=$C/ranker
mkdir -p "$R/in"
# the carried tables (RANK_IN: folders; a warm machine keeps those of earlier calls)
for d in ${RANK_IN:-out/ranker/in out/ranker/held}; do cp "$d"/*.npz "$R/in/" 2>/dev/null; done
declare -A VARIANTS=()
# RANK_VARIANTS="NAME=FLAGS ...": FLAGS with ',' between train_ranker flags, e.g.
# "main=--steps=1000 bce=--steps=1000,--list-weight=0,--bce-weight=1"
for spec in ${RANK_VARIANTS:-main=}; do v=${spec#*=}; VARIANTS[${spec%%=*}]=${v//,/ }; done
pairs_of() {  # NPZ... -> the pairs jsonl derive_dataset reads (pair_index + file)
    $PY - "$@" <<'EOF'
import sys, json, numpy as np
for p in sys.argv[1:]:
    with np.load(p) as z:
        for i, f in zip(z["pair_index"], z["files"]):
            print(json.dumps({"pair_index": int(i), "file": str(f)}))
EOF
}
derive() {  # SPLIT PAIRS WORKERS
    timeout -k 5 $(($(left) - 30)) $PY -m experiments.derive_dataset --data "$C/ds" --split "$1" \
        --workers "$3" --pairs-from "$2" --no-progress >>"$C/logs/derive_ranker_$1.log" 2>&1
    log "derived $1: $(ls "$C/ds/derived/$1" 2>/dev/null | wc -l) pair files"
}
if [ "$CALL" = train ] || [ "$CALL" = all ]; then
    for rec in "$C"/records/val_rank_*.pairs.jsonl.gz; do
        [ -e "$rec" ] || continue
        name=$(basename "$rec" .pairs.jsonl.gz)
        name=${name#val_}
        [ -e "$R/in/$name.npz" ] || $PY -m experiments.train_ranker slim "$rec" "$R/in/$name.npz" >>"$C/logs/slim.log" 2>&1
    done
    log "tables: $(ls "$R/in" | tr '\n' ' ')"
    pairs_of "$R"/in/rank_*.npz "$R"/in/val_*.npz >"$R/train_pairs.jsonl"
    pairs_of "$R"/in/held_*.npz | sort -u >"$R/test_pairs.jsonl"
    derive train "$R/train_pairs.jsonl" 16
    (derive test "$R/test_pairs.jsonl" 10) &
    DPID=$!
    PIDS=
    for name in "${!VARIANTS[@]}"; do
        log "ranker $name: ${VARIANTS[$name]}"
        XLA_PYTHON_CLIENT_MEM_FRACTION=$(awk "BEGIN {print 0.9 / ${#VARIANTS[@]}}") timeout -k 10 $(($(left) - 25)) $PY -m experiments.train_ranker train \
            --records "$R"/in/rank_*.npz --data "$C/ds" --init "${INIT_VALUE:-weights/value}" \
            --out "$R/$name" --val-records "$R"/in/val_*.npz --time-budget $((${RANK_TRAIN_BUDGET:-$((END_S - 70))} - $(date +%s) + T0)) \
            ${VARIANTS[$name]} --no-progress >>"$C/logs/ranker_$name.log" 2>&1 &
        PIDS="$PIDS $!"
    done
    for p in $PIDS; do wait "$p"; log "ranker run $p: exit $?"; done
    for name in "${!VARIANTS[@]}"; do
        log "$name: $(grep '^\[val\]' "$C/logs/ranker_$name.log" | tail -3 | tr '\n' ' ' | cut -c1-600)"
        (cd "$R" && tar -czf "$OUT/ranker_$name.tgz" "$name/value" "$name/metrics.jsonl" \
            "$name/val_metrics.jsonl" "$name/curves.png" "$name/summary.json" \
            -C "$C/logs" "ranker_$name.log" 2>/dev/null)
    done
    wait "$DPID"
    [ "$CALL" = all ] || { log "done"; exit 0; }
fi
if [ "$CALL" = score ] || [ "$CALL" = all ]; then
    [ -s "$R/test_pairs.jsonl" ] || pairs_of "$R"/in/held_*.npz | sort -u >"$R/test_pairs.jsonl"
    [ "$(ls "$C/ds/derived/test" 2>/dev/null | wc -l)" -ge 1794 ] || derive test "$R/test_pairs.jsonl" 16
    RANKERS=
    for name in "${!VARIANTS[@]}"; do
        [ -d "$R/$name/value" ] && RANKERS="$RANKERS $name=$R/$name/value" || log "no ranker $name"
    done
    for split in train test; do
        files=$([ $split = train ] && ls "$R"/in/val_*.npz || ls "$R"/in/held_*.npz)
        timeout $(($(left) - 5)) $PY -m experiments.train_ranker score --ranker $RANKERS \
            --records $files --data "$C/ds" --split $split --out "$OUT/score_$split.json" \
            --no-progress 2>&1 | tail -20 | tee -a "$OUT/$LOG"
    done
    log "done"
    exit 0
fi
echo "unknown call $CALL" >&2
exit 2
