#!/usr/bin/env bash
# The GPU measurement of dataset generation: paper-dataset generation with `--backend mjx`
# (MuJoCo Warp, every pair of a 32-pair shard in one GPU call per round).
#
# Run as the last of the warp-bundle calls (scripts/device_bench.md), after join + install
# into /tmp/site:  bash scripts/device_generate.sh
#
# Phase 1: one generator process on part MJX_PARTS[0] (its first group includes MuJoCo
#          Warp's kernel compilation, ~150-235 s on a fresh machine; cached in ~/.cache/warp),
#          SHARDS_PER_CALL shards per device model, CPU_WORKERS processes for the per-pair
#          CPU stage (collision labels, views) of one group while the GPU labels the next.
# Phase 2 (MJX_PROCS > 1; 2026-11-21: 4 processes of one shard each failed on Warp GPU
#          allocations at their second shard): more processes on the other parts.
# FRESH=1: ignore the shards already in DATA (measure on a finished dataset).
# ONE_MODEL=1: one process per group (--max-shards SHARDS_PER_CALL), restarted until END_S:
#          MuJoCo Warp's in-step allocations fail after a few device models in one process.
# No group is started after END_S (running ones finish; the hard stop at KILL_S loses only
# unfinished shards, never a written one).
# Everything comes back in $OUT as: device_generate.log, mjx_shards.tgz (new shards +
# runs.jsonl with one line per process: pairs, seconds, stage seconds, shards),
# shard_times.txt (shard, seconds after start), smi.csv (GPU utilisation every 5 s).
set -uo pipefail
T0=$(date +%s)
OUT=${OUT:-/tmp/out}
DATA=${DATA:-datasets/paper}
MJX_PROCS=${MJX_PROCS:-1}
SHARDS_PER_CALL=${SHARDS_PER_CALL:-4}
CPU_WORKERS=${CPU_WORKERS:-12}
MJX_PARTS=${MJX_PARTS:-"0/8 1/8 2/8 3/8"}
END_S=${END_S:-420}
KILL_S=${KILL_S:-560}
G=/tmp/gmjx
mkdir -p "$OUT" "$G/shards"
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
log() { echo "[$(($(date +%s) - T0)) s] $*" | tee -a "$OUT/device_generate.log"; }
nvidia-smi -L | tee -a "$OUT/device_generate.log"
nvidia-smi --query-gpu=timestamp,utilization.gpu,memory.used --format=csv -l 5 >"$OUT/smi.csv" &
SMI=$!
cp "$DATA/recipe.json" "$G/"
# FRESH=1: start from no shards (a throughput measurement on a finished dataset; the shards
# it makes are compared with the committed CPU ones afterwards)
[ -n "${FRESH:-}" ] || cp "$DATA"/shards/shard_*.npz "$G/shards/" 2>/dev/null
ls "$G/shards" >/tmp/mjx_before.txt
log "$(wc -l </tmp/mjx_before.txt) shards already done"

gen1() {  # part, seconds left for starting shards: one process
    python3 -m experiments.generate_dataset --preset paper --out "$G" --backend mjx \
        --part "$1" --stop-after "$2" --shards-per-call "$SHARDS_PER_CALL" \
        ${ONE_MODEL:+--max-shards "$SHARDS_PER_CALL"} \
        --workers "$CPU_WORKERS" --no-progress >>"$OUT/generate_${1/\//of}.log" 2>&1
}
gen() {  # ONE_MODEL=1: a new process per device model (group), until END_S or the part is done
    if [ -z "${ONE_MODEL:-}" ]; then
        gen1 "$@"
        return
    fi
    while [ $(($(date +%s) - T0)) -lt "$END_S" ]; do
        before=$(ls "$G/shards" | wc -l)
        gen1 "$1" $((END_S - $(date +%s) + T0))
        rc=$?
        log "part $1: process exited $rc, $(($(ls "$G/shards" | wc -l) - before)) new shards"
        [ "$rc" = 0 ] && [ "$(ls "$G/shards" | wc -l)" = "$before" ] && break  # part done
        [ "$rc" = 0 ] || [ "$rc" = 3 ] || break
    done
}
new_shards() { comm -13 /tmp/mjx_before.txt <(ls "$G/shards") | grep -c '^shard_'; }

set -- $MJX_PARTS
first=$1
shift
gen "$first" $((END_S - $(date +%s) + T0)) &
pids=($!)
while [ "$(new_shards)" -eq 0 ] && kill -0 "${pids[0]}" 2>/dev/null &&
    [ $(($(date +%s) - T0)) -lt "$END_S" ]; do
    sleep 2
done
log "first mjx shard written (includes Warp compilation): $(new_shards) new"
for p in "$@"; do
    [ ${#pids[@]} -ge "$MJX_PROCS" ] && break
    left=$((END_S - $(date +%s) + T0))
    [ "$left" -gt 0 ] || break
    gen "$p" "$left" &
    pids+=($!)
    log "started part $p (pid $!)"
done
alive() { for p in "${pids[@]}"; do kill -0 "$p" 2>/dev/null && return 0; done; return 1; }
while [ $(($(date +%s) - T0)) -lt "$KILL_S" ] && alive; do
    sleep 3
done
kill "${pids[@]}" 2>/dev/null  # the ONE_MODEL loops first, so that they start nothing new
pkill -f "out $G" && log "stopped generators still running at ${KILL_S} s"
sleep 2
kill $SMI 2>/dev/null
cd "$G" || exit 1
comm -13 /tmp/mjx_before.txt <(ls shards) | grep '^shard_' >/tmp/mjx_new.txt
while read -r f; do
    echo "$f $(($(stat -c %Y "shards/$f") - T0))"
done </tmp/mjx_new.txt >"$OUT/shard_times.txt"
sed 's|^|shards/|' /tmp/mjx_new.txt >/tmp/mjx_new_paths.txt
tar -czf "$OUT/mjx_shards.tgz" -T /tmp/mjx_new_paths.txt runs.jsonl "$OUT"/generate_*.log 2>/dev/null
rm -f "$OUT"/generate_*.log
log "new shards: $(wc -l </tmp/mjx_new.txt); $(cat runs.jsonl 2>/dev/null | wc -l) runs logged; done"
