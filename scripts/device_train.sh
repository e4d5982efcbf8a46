#!/usr/bin/env bash
# One GPU device call: derive the generated dataset's training pairs on all CPU
# cores, train Stages 1 / 2a / 2b on the GPU under time budgets, measure inference latency,
# and keep the CPU busy generating more dataset shards while the GPU trains.
#
#   run(carry=[".whl_min", ".whl_train"], timeout_s=600, command="bash scripts/device_train.sh")
#
# The carried wheels (docs/device.md): .whl_min (mujoco, mujoco_core, trimesh for Python 3.12)
# and .whl_train (jaxlie, jax_dataclasses). The device image has jax (CUDA), flax, optax,
# orbax, scipy, matplotlib, tqdm.
# Everything comes back in $OUT as three files (the device returns at most 8 files of
# 16 MiB): device_train.log, new_shards.tgz and results.tgz (the run's configs, metrics,
# loss curves, throughput.json per stage, the final weights from train.export_weights,
# bench_where.json and the logs).
# Environment knobs: DATA (default datasets/paper), PRESET (small), BATCH (32),
# GEN_S (0: generate on all cores first, starting no shard after GEN_S s; the phase lasts
# about GEN_S + one shard, ~3-4 min per 32-pair paper shard per core there), DERIVE_S (170), S1 / S2A / S2B (stage budgets in s), GEN_PART (0/8), END_S (555);
# GEN_ONLY=1: stop after the generation phase (a CPU-throughput call); TRAIN_ARGS: more
# experiments.train_where flags (e.g. "--augment-object-turn 32 --init-from weights/stage12 --stage1 rotation=6d" for
# Stages 1-2 that read objects in any frame);
# DERIVE_ARGS: more experiments.derive_dataset flags (e.g. "--clouds-only --camera-scale 0.5":
# Stage 1's training clouds, ~5x less CPU a pair; then STAGE=1); STAGE (train_where --stage,
# default all; "canon": the object-frame network, budget SCANON s, default 300); GEN_BG=0: no background shard generation while training. The exported weights
# also stay on the machine in /tmp/export (a warm next call reads them there).
# SKIP_INSTALL=1 for a dry run here (with .venv/bin first on PATH).
set -uo pipefail
T0=$(date +%s)
OUT=${OUT:-/tmp/out}
DATA=${DATA:-datasets/paper}
PRESET=${PRESET:-small}
BATCH=${BATCH:-32}
DERIVE_S=${DERIVE_S:-170}
S1=${S1:-170}
S2A=${S2A:-70}
S2B=${S2B:-50}
GEN_PART=${GEN_PART:-0/8}
END_S=${END_S:-555}
mkdir -p "$OUT"
# stage budgets exclude loading the data to the GPU and compiling (~40-90 s in all)
if [ $((DERIVE_S + S1 + S2A + S2B + 90)) -gt "$END_S" ]; then
    echo "warning: DERIVE_S + S1 + S2A + S2B + 90 s > END_S ($END_S s): the call may end before its tarballs" >&2
fi
log() { echo "[$(($(date +%s) - T0)) s] $*" | tee -a "$OUT/device_train.log"; }

[ -n "${SKIP_INSTALL:-}" ] || python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site \
    .whl_min/*.whl .whl_train/*.whl || exit 5
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
nvidia-smi -L | tee -a "$OUT/device_train.log"
log "installed; $(ls "$DATA/shards" | wc -l) shards in $DATA"

# 1. generate more shards on all cores first (GEN_S seconds; killed shards are not written)
mkdir -p /tmp/gen/shards && cp "$DATA/recipe.json" /tmp/gen/
cp "$DATA"/shards/shard_*.npz /tmp/gen/shards/ 2>/dev/null
ls /tmp/gen/shards >/tmp/gen_before.txt
gen() {  # workers, start no shard after this many seconds (running shards finish)
    timeout -s TERM "${GEN_HARD_S:-100000}" python3 -m experiments.generate_dataset --preset paper --out /tmp/gen \
        --part "$GEN_PART" --workers "$1" --stop-after "$2" --no-progress >>"$OUT/generate.log" 2>&1
}
if [ "${GEN_S:-0}" -gt 0 ]; then
    GEN_HARD_S=${GEN_HARD_S:-$((GEN_S + 250))} gen 16 "$GEN_S"  # SIGTERM: written shards stay
    log "generated $(($(ls /tmp/gen/shards | wc -l) - $(wc -l </tmp/gen_before.txt))) new shards in $GEN_S s on 16 workers"
fi
if [ -n "${GEN_ONLY:-}" ]; then  # a generation-only call: bring back the new shards, stop
    cd /tmp/gen && comm -13 /tmp/gen_before.txt <(ls shards) | grep '^shard_' | sed 's|^|shards/|' >/tmp/new.txt
    tar -czf "$OUT/new_shards.tgz" -T /tmp/new.txt runs.jsonl "$OUT/generate.log" 2>/dev/null
    log "new shards: $(wc -l </tmp/new.txt); generation only, done"
    exit 0
fi

# 2. derive the training split (resumable; whatever is derived when the budget ends is used)
mkdir -p /tmp/ds && cp -r /tmp/gen/recipe.json /tmp/gen/shards /tmp/ds/
timeout -k 5 "$DERIVE_S" python3 -m experiments.derive_dataset --data /tmp/ds --split train \
    --workers 0 --no-progress ${DERIVE_ARGS:-} >"$OUT/derive.log" 2>&1
pkill -f "derive_dataset --data /tmp/ds"
TRAIN_DATA=$(dirname "$(find /tmp/ds/derived -name '*.npz' | head -1)")
log "derived $(ls "$TRAIN_DATA" 2>/dev/null | wc -l) training pairs in $TRAIN_DATA"

# the CPU cores the trainer does not need generate more shards in the background; a shard
# takes ~3 min per worker there, so none is started later than 200 s before the end
[ "${GEN_BG:-1}" = 0 ] ||
    setsid bash -c "$(declare -f gen); OUT=$OUT GEN_PART=$GEN_PART gen 12 $((END_S - 200 - $(date +%s) + T0))" &

# 3. train on the GPU
python3 -m experiments.train_where --data "$TRAIN_DATA" --out /tmp/run --preset "$PRESET" \
    --stage "${STAGE:-all}" --batch "$BATCH" --steps "${STEPS:-1000000}" --time-budget "1=$S1,2a=$S2A,2b=$S2B,canon=${SCANON:-300}" --data-on-device --no-progress \
    ${TRAIN_ARGS:-} \
    >"$OUT/train.log" 2>&1
log "trained: $(tail -1 "$OUT/train.log")"

# 4. export the weights, inference latency
python3 -c "from omnihang_jax import train; train.export_weights('/tmp/run', '$OUT/weights')" \
    >>"$OUT/device_train.log" 2>&1
rm -rf /tmp/export && cp -r "$OUT/weights" /tmp/export
# the latency benchmark needs ~45 s; skip it when the call's end is nearer than that (a call
# that runs past its limit loses its tarballs)
if [ -z "${NO_BENCH:-}" ] && [ $((END_S - $(date +%s) + T0)) -gt 70 ]; then
    timeout 60 python3 -m experiments.bench_where --model /tmp/run --out "$OUT/bench_where.json" \
        >>"$OUT/device_train.log" 2>&1
else
    log "skipped bench_where: less than 70 s left before END_S"
fi
for s in stage1 stage2a stage2b stagecanon; do
    [ -d /tmp/run/$s ] || continue
    mkdir -p "$OUT/run/$s" && cp /tmp/run/$s/{config.json,metrics.jsonl,val_metrics.jsonl,loss.png,throughput.json} \
        "$OUT/run/$s/" 2>/dev/null
done

# 5. stop the generator before the call's limit; bring back only the new shards
while [ $(($(date +%s) - T0)) -lt "$END_S" ] && pgrep -f "out /tmp/gen" >/dev/null; do
    sleep 5
done
pkill -f "out /tmp/gen"
sleep 2
cd /tmp/gen && ls shards >/tmp/gen_after.txt
comm -13 /tmp/gen_before.txt /tmp/gen_after.txt | grep '^shard_' | sed 's|^|shards/|' >/tmp/new.txt
tar -czf "$OUT/new_shards.tgz" -T /tmp/new.txt runs.jsonl 2>/dev/null
log "new shards: $(wc -l </tmp/new.txt); done"
# the device returns at most 8 files per call: everything else goes into one tarball
cd "$OUT" || exit 1
items=$(ls -d run weights bench_where.json derive.log train.log generate.log 2>/dev/null)
tar -czf results.tgz $items && rm -rf $items
