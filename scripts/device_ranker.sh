#!/usr/bin/env bash
# The answer's rankers (experiments.train_ranker, weights/rankers/) on one GPU: pools of the
# pipeline's simulated candidates, then fine-tuning. Each call stops itself before END_S and
# leaves its state resumable on the machine ($C); what must outlive the machine comes back.
#
#   run(carry=[".whl_min", ".whl_train"], command="PAIRS=4840 bash scripts/device_ranker.sh pools")
#   run(carry=[".whl_min", ".whl_train", "out/ranker/pools"],
#       command="RANK_IN=out/ranker/pools RANK_VARIANTS='listwise=--steps=2500' bash scripts/device_ranker.sh train")
#
# CALL
#   pools  derives the training split's pair files not yet on the machine (all ~12k: ~7 min on
#          16 cores, so the first call or two only derive; DERIVE_S caps it, default until 150 s
#          are left; resumable), then, once all are there, pools the validation objects' pairs
#          (VAL_PAIRS, default all) and PAIRS training pairs (default 4840; a balanced prefix,
#          so a larger PAIRS extends the same pools) with `train_ranker pools` (networks on the
#          GPU, the simulation in CORES - 1 processes, BATCH pairs a network call, default 32).
#          Back in $OUT: pools.tgz (pools/ and val_pools/: every shard so far, ~2 kB a pair) and
#          ranker.log. A call cut short keeps its shards: the next call (warm, or with the
#          tarball carried and unpacked by RANK_IN) goes on from there.
#   train  trains each of RANK_VARIANTS ("NAME=FLAGS ...", FLAGS with ',' between train_ranker
#          flags, e.g. "listwise=--steps=2500 near=--steps=2500,--support-near=256,--object-near=256")
#          side by side on the GPU on the pools ($C/ranker, or those carried in RANK_IN: a folder
#          holding pools/ and val_pools/, or pools.tgz), from INIT_VALUE (default weights/value),
#          for at most RANK_TRAIN_BUDGET seconds of the call (default END_S - 40), after deriving
#          the pools' pair files not on the machine (~3 min for 5k pairs). Back in $OUT:
#          ranker_NAME.tgz (value/, metrics, validation, curves, summary, log).
#   all    pools, then train, in one call.
set -uo pipefail
CALL=${1:?usage: device_ranker.sh pools|train|all}
C=${C:-/tmp/ranker}
END_S=${END_S:-580}
LOG=ranker.log
. scripts/device_preamble.sh
export JAX_COMPILATION_CACHE_DIR=$C/jax_cache
DS=$C/ds
R=$C/ranker
CORES=$(nproc)
mkdir -p "$R"
# carried pools (RANK_IN: a folder with pools/ + val_pools/, or pools.tgz) join the machine's
for d in ${RANK_IN:-}; do
    if [ -s "$d/pools.tgz" ]; then
        tar -xzf "$d/pools.tgz" -C "$R"
    else
        for sub in pools val_pools; do
            [ -d "$d/$sub" ] && mkdir -p "$R/$sub" && cp -n "$d/$sub"/shard_*.npz "$R/$sub/" 2>/dev/null
        done
    fi
done
shards() { ls "$R/$1" 2>/dev/null | wc -l; }
log "pools on the machine: $(shards pools) training shards, $(shards val_pools) validation shards"

if [ "$CALL" = pools ] || [ "$CALL" = all ]; then
    n=$(ls "$DS/derived/train" 2>/dev/null | wc -l)
    timeout -k 5 "${DERIVE_S:-$(($(left) - 150))}" $PY -m experiments.derive_dataset --data "$DS" \
        --split train --workers "$CORES" --no-progress >>"$C/logs/derive.log" 2>&1
    rc=$?
    log "derive: rc $rc, $(($(ls "$DS/derived/train" 2>/dev/null | wc -l) - n)) training pairs now, $(ls "$DS/derived/train" | wc -l) in all"
    # the balanced prefix is over every training pair: pool only once all are derived
    [ $rc = 0 ] || { log "derive cut short: call again (it resumes)"; exit 0; }
    for split in validation train; do
        dir=$([ $split = train ] && echo pools || echo val_pools)
        pairs=$([ $split = train ] && echo "${PAIRS:-4840}" || echo "${VAL_PAIRS:-}")
        timeout -k 10 $(($(left) - 20)) $PY -m experiments.train_ranker pools --data "$DS" \
            --split $split ${pairs:+--pairs $pairs} --out "$R/$dir" --batch "${BATCH:-32}" \
            --workers $((CORES - 1)) --no-progress >>"$C/logs/pools_$split.log" 2>&1
        log "pools $split: rc $? ($(tail -1 "$C/logs/pools_$split.log" | cut -c1-200))"
    done
    (cd "$R" && tar -czf "$OUT/pools.tgz" pools val_pools 2>/dev/null)
    log "pools.tgz: $(shards pools) training shards, $(shards val_pools) validation shards"
    [ "$CALL" = all ] || { log "done"; exit 0; }
fi
if [ "$CALL" = train ] || [ "$CALL" = all ]; then
    [ "$(shards pools)" -gt 0 ] || { log "no pools: run the pools call first"; exit 1; }
    # the pools' pair files (a warm machine has them; a fresh one derives those pairs)
    $PY - "$R/pools" "$R/val_pools" >"$R/pairs.jsonl" <<'EOF'
import json, sys
from omnihang_jax.pools import pooled_pairs
for i in sorted(set().union(*map(pooled_pairs, sys.argv[1:]))):
    print(json.dumps({"pair_index": i}))
EOF
    timeout -k 5 $(($(left) / 2)) $PY -m experiments.derive_dataset --data "$DS" --split train \
        --pairs-from "$R/pairs.jsonl" --workers "$CORES" --no-progress >>"$C/logs/derive.log" 2>&1
    declare -A VARIANTS=()
    for spec in ${RANK_VARIANTS:-listwise=}; do v=${spec#*=}; VARIANTS[${spec%%=*}]=${v//,/ }; done
    VAL=$([ "$(shards val_pools)" -gt 0 ] && echo "--val-pools $R/val_pools")
    PIDS=
    for name in "${!VARIANTS[@]}"; do
        log "ranker $name: ${VARIANTS[$name]}"
        XLA_PYTHON_CLIENT_MEM_FRACTION=$(awk "BEGIN {print 0.9 / ${#VARIANTS[@]}}") \
            timeout -k 10 $(($(left) - 25)) $PY -m experiments.train_ranker train \
            --pools "$R/pools" $VAL --data "$DS" --init "${INIT_VALUE:-weights/value}" \
            --out "$R/$name" --time-budget $((${RANK_TRAIN_BUDGET:-$((END_S - 40))} - $(date +%s) + T0)) \
            ${VARIANTS[$name]} --no-progress >>"$C/logs/ranker_$name.log" 2>&1 &
        PIDS="$PIDS $!"
    done
    for p in $PIDS; do wait "$p"; log "ranker run $p: exit $?"; done
    for name in "${!VARIANTS[@]}"; do
        log "$name: $(grep '^\[val\]' "$C/logs/ranker_$name.log" | tail -2 | tr '\n' ' ' | cut -c1-400)"
        (cd "$R" && tar -czf "$OUT/ranker_$name.tgz" "$name/value" "$name/metrics.jsonl" \
            "$name/val_metrics.jsonl" "$name/curves.png" "$name/summary.json" \
            -C "$C/logs" "ranker_$name.log" 2>/dev/null)
    done
    log "done"
    exit 0
fi
echo "unknown call $CALL" >&2
exit 2
