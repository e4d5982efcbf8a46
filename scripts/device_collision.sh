#!/usr/bin/env bash
# One GPU device call: derive the clouds and collision labels of training and held-out pairs
# on all CPU cores, train the NCE (train_collision's defaults: planner labels, 100 far free
# poses per pair, the stable poses free, a near-contact share of 0.3, cosine lr) and the HCE
# normal net on the GPU under time budgets, print held-out accuracy / precision / recall,
# benchmark the batched estimators, and bring back the small weights.
#
#   run(carry=[".whl_min", ".whl_train"], timeout_s=600,
#       command="bash scripts/device_collision.sh")
#
# (.whl_min / .whl_train as in docs/device.md. The image has jax (CUDA), flax, optax, numpy,
# scipy, matplotlib, tqdm. OMPL is not needed here: planning runs on the CPU.)
# Everything comes back in $OUT: device_collision.log (the metrics are printed there and on
# stdout) and results.tgz (weights/{nce,hce_normals}/, hce_true_normals.json, metrics.json,
# bench_paths_gpu.json, the logs). Unpack with `tar -xzf results.tgz`.
# Environment knobs: DATA (datasets/paper), PRESET (contact; collision.NCE_PRESETS),
# N_TRAIN (3000 pairs), N_TEST (400), DERIVE_S (180: held-out pairs first, then training
# pairs; whatever is derived by then is used), NCE_S (190), NORMALS_S (40), BATCH (256),
# END_S (570); SKIP_INSTALL=1 for a dry run here (with .venv/bin first on PATH).
set -uo pipefail
T0=$(date +%s)
OUT=${OUT:-/tmp/out}
DATA=${DATA:-datasets/paper}
PRESET=${PRESET:-contact}
N_TRAIN=${N_TRAIN:-3000}
N_TEST=${N_TEST:-400}
DERIVE_S=${DERIVE_S:-180}
NCE_S=${NCE_S:-190}
NORMALS_S=${NORMALS_S:-40}
BATCH=${BATCH:-256}
END_S=${END_S:-570}
mkdir -p "$OUT"
log() { echo "[$(($(date +%s) - T0)) s] $*" | tee -a "$OUT/device_collision.log"; }
if [ $((DERIVE_S + NCE_S + NORMALS_S + 120)) -gt "$END_S" ]; then
    log "warning: the budgets + ~120 s of install, compilation and evaluation exceed END_S ($END_S s)"
fi

[ -n "${SKIP_INSTALL:-}" ] || python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site \
    .whl_min/*.whl .whl_train/*.whl || exit 5
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
nvidia-smi -L 2>/dev/null | tee -a "$OUT/device_collision.log"
log "installed; $(ls "$DATA/shards" | wc -l) shards in $DATA"

# 1. derive (clouds + collision labels, cached under DATA/derived/collision): the held-out
#    pairs first, then as many training pairs as DERIVE_S allows (each file is complete)
timeout -k 5 "$DERIVE_S" python3 -m experiments.train_collision --data "$DATA" --out /tmp/col \
    --train-pairs "$N_TRAIN" --test-pairs "$N_TEST" --derive-only --workers 0 --no-progress \
    >"$OUT/derive.log" 2>&1
log "derived $(ls "$DATA/derived/collision/train" | wc -l) training, $(ls "$DATA/derived/collision/test" | wc -l) held-out pairs"

# 2. train on the GPU, thresholds on training labels, metrics on held-out labels
python3 -m experiments.train_collision --data "$DATA" --out /tmp/col --preset "$PRESET" \
    --train-pairs "$N_TRAIN" --test-pairs "$N_TEST" --existing-only --batch "$BATCH" \
    --normal-batch 32 --time-budget "nce=$NCE_S,normals=$NORMALS_S" --eval-labels 50000 \
    --threshold-labels 30000 --no-progress >"$OUT/train.log" 2>&1
grep -E "^pairs:|^held-out" "$OUT/train.log" | tee -a "$OUT/device_collision.log"
python3 -c "import json; m = json.load(open('/tmp/col/metrics.json')); print({k: {x: m[k][x] for x in ('steps', 'train_s', 'samples_per_s')} for k in ('nce', 'normals')})" \
    2>&1 | tee -a "$OUT/device_collision.log"
log "trained"

# 3. queries per second of the batched estimators on this GPU (skipped when END_S is near)
LEFT=$((END_S - $(date +%s) + T0))
if [ "$LEFT" -gt 20 ]; then
    timeout $((LEFT - 5)) python3 -m experiments.bench_paths --weights /tmp/col --out "$OUT/bench_paths_gpu.json" \
        --batches 1,64,1024,4096,16384 >>"$OUT/device_collision.log" 2>&1
else
    log "skipped bench_paths: less than 20 s left before END_S"
fi
log "done"

# the device returns at most 8 files per call: everything else goes into one tarball
mkdir -p "$OUT/weights" && cp -r /tmp/col/nce /tmp/col/hce_normals /tmp/col/hce_true_normals.json \
    /tmp/col/metrics.json "$OUT/weights/" 2>/dev/null
cd "$OUT" || exit 1
items=$(ls -d weights bench_paths_gpu.json derive.log train.log 2>/dev/null)
tar -czf results.tgz $items && rm -rf $items
