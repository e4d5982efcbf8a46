#!/usr/bin/env bash
# The headline figures on the device machine, one foreground call: `experiments.evaluate where`
# (held-out pairs derived first on the 16 CPU cores; the networks on the GPU, the simulation in
# 15 processes), `experiments.evaluate paths` (planning on the CPU cores) and
# `experiments.bench_where` (latency of the answer). The tree must travel lean
# (scripts/device_lean.sh out MODE first, back after):
#
#   run(carry=[".whl_min", ".whl_train"], timeout_s=600,
#       command="MODE=where bash scripts/device_evaluate.sh")
#   run(carry=[".whl_min", ".whl_train", ".whl_plan"], timeout_s=600,
#       command="MODE=paths bash scripts/device_evaluate.sh")
#
# MODE: steps run in the order given, among "where", "paths" and "bench" (default "where").
# where: derives the held-out pairs not yet on the machine (all of them, or the first PAIRS + 16
#   round robin over the categories, so that `--pairs PAIRS` finds its whole sample), then runs
#   every CONFIG (default "default"; "default paper" runs both) on PAIRS pairs (default: all
#   derived), seeds SEEDS (default "0 1 2"), BATCH pairs per network call (default 4: the
#   default answer needs ~2 GiB of GPU memory a pair; 16 runs out of an H100's 80 GB);
#   DERIVE_S caps the derive (default: until 120 s are left); FRAME=any runs the any-frame
#   protocol (records where_CONFIG_any_frame.jsonl, results key CONFIG_any_frame); NOISE (mm)
#   and DROPOUT (a share) degrade the clouds (--depth-noise, --dropout: records and key gain
#   _noise<NOISE>mm / _dropout<percent>).
# paths: PATHS_CONFIG (default "default"), PATHS_PAIRS (default 300), PATHS_SEEDS (default 1),
#   16 planning processes (needs .whl_plan); FRAME=any plans each object in a random frame
#   (records paths_CONFIG_any_frame.jsonl).
# bench: bench_where over BENCH_CONFIGS (default,paper), BENCH_BATCHES (1,8,64,256), BENCH_REPEAT (10).
# Each step stops itself before END_S (default 560 s) and leaves its records resumable: a warm
# next call resumes from the machine's copy, a fresh one from RESUME=DIR (a carried folder
# holding an earlier call's $OUT files). Back in $OUT: evaluate.log (timings, the summaries),
# where_CONFIG.jsonl.gz and paths_CONFIG.jsonl.gz (per-pair records), paths_CONFIG.config.json,
# where_results.json / paths_results.json (the evaluate summaries of finished runs, one key per
# config, to merge into results/hanging_success.json / results/paths.json) and bench_where.json.
# A dry run here: SKIP_INSTALL=1 PY=.venv/bin/python OUT=/tmp/devout PAIRS=4 SEEDS=0 MODE=where.
set -uo pipefail
CALL=evaluate
C=${C:-/tmp/evaluate}
END_S=${END_S:-560}
LOG=evaluate.log
. scripts/device_preamble.sh
export JAX_COMPILATION_CACHE_DIR=$C/jax_cache
DS=$C/ds
mkdir -p "$C/rec"
CORES=$(nproc)
log "$CORES cores; MODE=${MODE:=where}; $(git rev-parse --short HEAD 2>/dev/null || echo no-git)"

# the records of NAME (e.g. where_default.jsonl) into $OUT: the machine's copy, else RESUME's
restore() {
    if [ -s "$C/rec/$1" ]; then
        cp "$C/rec/$1" "$OUT/$1"
    elif [ -n "${RESUME:-}" ] && [ -s "$RESUME/$1.gz" ]; then
        gunzip -c "$RESUME/$1.gz" >"$OUT/$1"
    elif [ -n "${RESUME:-}" ] && [ -s "$RESUME/$1" ]; then
        cp "$RESUME/$1" "$OUT/$1"
    fi
    [ -s "$OUT/$1" ] && log "$1: resuming from $(wc -l <"$OUT/$1") rows"
}
# keep the records on the machine and send them back gzipped
keep() {
    [ -s "$OUT/$1" ] || return 0
    cp "$OUT/$1" "$C/rec/$1"
    gzip -f "$OUT/$1"
}
# the project's summary of the records, whole or cut short (the means in the log)
summary() {  # figure records
    $PY - "$@" <<'EOF' 2>&1 | tee -a "$OUT/$LOG"
import json, sys
from omnihang_jax import paths_eval, where_eval
figure, path = sys.argv[1:]
mod = where_eval if figure == "where" else paths_eval
rows = mod.read_records(path)
if rows:
    s = mod.summarise(rows)
    if figure == "where":
        s = {k: {"mean": v["mean"], "pairs": v["pairs"]} for k, v in s.items()}
    else:
        s = {k: v for k, v in s.items() if not isinstance(v, dict)}
    print(f"{figure} summary of {len(rows)} rows:", json.dumps(s))
EOF
}
run_step() {  # name seconds command...: the command under a time limit, its tail in the log
    local name=$1 secs=$2 t=$(date +%s) rc
    shift 2
    if [ "$secs" -lt 30 ]; then
        log "$name: no time left"
        return 124
    fi
    timeout -k 10 "$secs" "$@" >"$C/logs/$name.log" 2>&1
    rc=$?
    grep -v "leaked\|nanobind\|^ - \|it/s\]\|s/it\]" "$C/logs/$name.log" | tail -n "${TAIL:-4}" >>"$OUT/$LOG"
    log "$name: rc $rc after $(($(date +%s) - t)) s$([ $rc = 124 ] && echo ' (time limit: resumable)')"
    return $rc
}

where_step() {
    local t n
    n=$(ls "$DS/derived/test" 2>/dev/null | wc -l)
    log "derive: $n held-out pairs on the machine"
    t=$(date +%s)
    TAIL=0 run_step derive "${DERIVE_S:-$(($(left) - 120))}" $PY -m experiments.derive_dataset --data "$DS" \
        --split test --workers "${DERIVE_WORKERS:-$CORES}" --no-progress \
        ${PAIRS:+--limit $((PAIRS + 16 > n ? PAIRS + 16 - n : 0))}
    # a derive cut short writes no derived.json, which evaluate reads: a no-op derive writes it
    [ -s "$DS/derived/derived.json" ] || $PY -m experiments.derive_dataset --data "$DS" --split test \
        --limit 0 --no-progress >>"$C/logs/derive.log" 2>&1
    local m=$(ls "$DS/derived/test" 2>/dev/null | wc -l)
    log "derive: $((m - n)) pairs in $(($(date +%s) - t)) s; $m held-out pairs on the machine"
    [ "$m" -gt 0 ] || return 1
    for c in ${CONFIG:-default}; do
        # FRAME=any: the any-frame protocol (records where_CONFIG_any_frame.jsonl)
        local cfg=$c
        [ "${FRAME:-library}" = any ] && cfg=${c}_any_frame
        [ -n "${NOISE:-}" ] && cfg=${cfg}_noise${NOISE}mm
        [ -n "${DROPOUT:-}" ] && cfg=${cfg}_dropout$(awk "BEGIN {print 100 * $DROPOUT}")
        restore "where_$cfg.jsonl"
        t=$(date +%s)
        local before=$(cat "$OUT/where_$cfg.jsonl" 2>/dev/null | wc -l)
        run_step "where_$cfg" $(($(left) - 15)) $PY -m experiments.evaluate where \
            --config "$c" --frame "${FRAME:-library}" --data "$DS" --seed ${SEEDS:-0 1 2} --batch "${BATCH:-4}" \
            --depth-noise "${NOISE:-0}" --dropout "${DROPOUT:-0}" \
            --workers "${EVAL_WORKERS:-$((CORES - 1))}" ${PAIRS:+--pairs $PAIRS} --no-progress \
            --records "$OUT/where_$cfg.jsonl" --results "$OUT/where_results.json"
        local after=$(cat "$OUT/where_$cfg.jsonl" 2>/dev/null | wc -l)
        log "where $cfg: $((after - before)) new rows in $(($(date +%s) - t)) s ($after in all)"
        summary where "$OUT/where_$cfg.jsonl"
        keep "where_$cfg.jsonl"
    done
}

paths_step() {
    local c=${PATHS_CONFIG:-default} cfg=${PATHS_CONFIG:-default} t=$(date +%s)
    [ "${FRAME:-library}" = any ] && cfg=${cfg}_any_frame
    [ -n "${SKIP_INSTALL:-}" ] || [ -e /tmp/site/ompl ] || { log "paths: no ompl (carry .whl_plan)"; return 5; }
    restore "paths_$cfg.jsonl"
    [ -n "${RESUME:-}" ] && [ ! -s "$OUT/paths_$cfg.config.json" ] && [ -s "$RESUME/paths_$cfg.config.json" ] &&
        cp "$RESUME/paths_$cfg.config.json" "$OUT/"
    [ -s "$C/rec/paths_$cfg.config.json" ] && cp "$C/rec/paths_$cfg.config.json" "$OUT/"
    local before=$(cat "$OUT/paths_$cfg.jsonl" 2>/dev/null | wc -l)
    run_step "paths_$cfg" $(($(left) - 15)) $PY -m experiments.evaluate paths --config "$c" \
        --frame "${FRAME:-library}" \
        --data "$DS" --pairs "${PATHS_PAIRS:-300}" --seed ${PATHS_SEEDS:-1} \
        --workers "${PATHS_WORKERS:-$CORES}" --no-progress \
        --records "$OUT/paths_$cfg.jsonl" --results "$OUT/paths_results.json"
    local after=$(cat "$OUT/paths_$cfg.jsonl" 2>/dev/null | wc -l)
    log "paths $cfg: $((after - before)) new rows in $(($(date +%s) - t)) s ($after in all)"
    summary paths "$OUT/paths_$cfg.jsonl"
    [ -s "$OUT/paths_$cfg.config.json" ] && cp "$OUT/paths_$cfg.config.json" "$C/rec/"
    keep "paths_$cfg.jsonl"
}

bench_step() {
    TAIL=12 run_step bench $(($(left) - 10)) $PY -m experiments.bench_where \
        --configs "${BENCH_CONFIGS:-default,paper}" --batches "${BENCH_BATCHES:-1,8,64,256}" \
        --repeat "${BENCH_REPEAT:-10}" --out "$OUT/bench_where.json"
}

for step in $MODE; do
    case $step in
        where) where_step ;;
        paths) paths_step ;;
        bench) bench_step ;;
        *) log "unknown step $step (where, paths, bench)" ;;
    esac
done
log "done; back in \$OUT: $(ls "$OUT" | tr '\n' ' ')"
