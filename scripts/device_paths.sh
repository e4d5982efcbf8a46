#!/usr/bin/env bash
# Issue 13 on the device machine's CPU cores (twenty-fourth session): experiments.eval_paths runs
# planned by SHARDS processes at once (`eval_paths --shard I/N`), each pinned to CORES cores with
# JAX on the CPU, as one run plans on the 2-core VM; the variants one after another, side by side
# in one call. An 80-pair variant with --clear-path took ~32 min on the VM and ~9 min here with
# 8 shards (each process at about half the VM's speed: compare device runs with each other).
#
#   python scripts/slim_path_records.py results/hanging_success_stage3_s14_cemv.pairs.jsonl.gz \
#       out/paths_records.jsonl.gz
#   mkdir -p .whl_plan && pip download --no-deps --only-binary=:all: --python-version 3.12 \
#       --implementation cp --platform manylinux_2_17_x86_64 -d .whl_plan ompl==2.0.1
#   PATHS=1 MORE=1 bash scripts/device_slim.sh out
#   run(carry=[".whl_min", ".whl_train", ".whl_plan", "datasets/paper/derived/collision/test",
#              "out/paths_records.jsonl.gz"], timeout_s=600,
#       command="VARIANTS='best= clear=--clear-path,0.03' bash scripts/device_paths.sh")
#   bash scripts/device_slim.sh in
#
# VARIANTS: "NAME=FLAGS ..." (FLAGS comma-separated, added to the best hybrid's settings below;
# empty: the best hybrid itself). A warm next call resumes a variant cut short (the rows of
# /tmp/paths/NAME/pairs.jsonl stay); a fresh call resumes one from RESUME=DIR (carried), whose
# DIR/paths_NAME.pairs.jsonl rows (an earlier call's $OUT) are planned no more. Back in $OUT: paths.log, paths_NAME.json (the summary) and
# paths_NAME.pairs.jsonl (every row) per variant.
set -uo pipefail
CALL=paths
C=/tmp/paths
END_S=${END_S:-580}
LOG=paths.log
. scripts/device_preamble.sh
if [ ! -e /tmp/site/ompl ]; then
    $PY -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl_plan/*.whl ||
        { log "ompl install failed"; exit 5; }
fi
SHARDS=${SHARDS:-8}
CORES=${CORES:-2}
RECORDS=${RECORDS:-out/paths_records.jsonl.gz}
COMMON="--weights ${NCE_W:-weights/collision_s18_contact} --pairs ${PAIRS:-80} --methods nce_geometric
    --geometric results/paths_hybrid_s18_joint95_selection.json --time-limit ${TIME_LIMIT:-30}
    --pairs-from $RECORDS --goal stable --nce-threshold 0.99 --nce-far-threshold 0.56
    --nce-goal-ball 0.02 --no-progress"
export JAX_PLATFORMS=cpu
log "$(nproc) cores; $SHARDS shards x $CORES cores; variants: ${VARIANTS:-best=}"
for spec in ${VARIANTS:-best=}; do
    name=${spec%%=*} flags=${spec#*=}
    flags=${flags//,/ }
    [ "$(left)" -gt 90 ] || { log "no time left for $name"; break; }
    mkdir -p "$C/$name"
    if [ -n "${RESUME:-}" ] && [ -s "$RESUME/paths_$name.pairs.jsonl" ] && [ ! -s "$C/$name/pairs.jsonl" ]; then
        cp "$RESUME/paths_$name.pairs.jsonl" "$C/$name/pairs.jsonl"
        log "variant $name resumed from $RESUME: $(wc -l <"$C/$name/pairs.jsonl") rows"
    fi
    log "variant $name: $flags"
    pids=()
    for i in $(seq 0 $((SHARDS - 1))); do
        cores=$(seq -s, $((i * CORES)) $((i * CORES + CORES - 1)))
        timeout -k 5 $(($(left) - 60)) taskset -c "$cores" $PY -m experiments.eval_paths $COMMON \
            $flags --out "$C/$name" --shard "$i/$SHARDS" >"$C/logs/${name}_$i.log" 2>&1 &
        pids+=($!)
    done
    for p in "${pids[@]}"; do wait "$p"; done
    log "$name planned: $(wc -l <"$C/$name/pairs.jsonl") rows"
    timeout -k 5 $(($(left) - 5)) $PY -m experiments.eval_paths $COMMON $flags --out "$C/$name" \
        --summary-only --results "$OUT/paths_$name.json" 2>&1 | grep -v "leaked\|nanobind\|^ - " |
        tail -3 | tee -a "$OUT/$LOG"
    cp "$C/$name/pairs.jsonl" "$OUT/paths_$name.pairs.jsonl"
done
log "done"
