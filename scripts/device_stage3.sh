#!/usr/bin/env bash
# Stage 3 on one GPU machine. Every mode is ONE foreground device call (<= 10 min): a job
# spread over calls is lost when the next call misses the machine's 30-s warm window.
#
#   run(carry=[".whl_min", ".whl_train"], timeout_s=600, command="bash scripts/device_stage3.sh MODE")
#
#   train     derive NTRAIN training pairs (round robin over categories) on all cores, train V
#             (experiments.train_stage3, preset paper, TRAIN_S budget: seed buffer, pretrain,
#             RL rounds); back: $OUT/stage3.tgz (run/ without buffer and train state: value/,
#             metrics, rounds, curves, split) + logs. Measured: 167 s derive + 318 s training.
#   curve     the refinement-learning curve (experiments.refinement_learning)
# Knobs: NTRAIN (3000), TRAIN_S (360), PRETRAIN (6000), ROUNDS (8), CURVE_S (300).
# The held-out evaluation of the answer is scripts/device_evaluate.sh.
# V on ALL training pairs with hard-negative rounds (weights/value) is the chain part
# scripts/chain/stage3.sh (2-3 calls, resumable), not a mode here.
set -uo pipefail
MODE=${1:?usage: device_stage3.sh train|curve}
OUT=${OUT:-/tmp/out}
W=/tmp/s3
T0=$(date +%s)
mkdir -p "$OUT" "$W"
setup_env() {  # the carried wheels into /tmp/site; this tree on the path
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site \
        .whl_min/*.whl .whl_train/*.whl || return 5
    export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
}

if [ "$MODE" = curve ]; then
    # one call: the refinement-learning curve (100 training pairs, 10,000 steps, Stage-2 vs
    # uniform start)
    setup_env || exit 5
    nvidia-smi -L | tee "$OUT/curve.log"
    python3 -m experiments.derive_dataset --data datasets/paper --split train --limit 400 \
        --workers 16 --no-progress >/dev/null 2>&1
    timeout ${CURVE_S:-300} python3 -m experiments.refinement_learning --workers 10 \
        --out "$OUT/refinement_learning.json" --no-progress 2>&1 | tail -3 | tee -a "$OUT/curve.log"
    echo "[$(($(date +%s) - T0)) s] curve" | tee -a "$OUT/curve.log"
    echo "[$(($(date +%s) - T0)) s] done" | tee -a "$OUT/curve.log"
    exit 0
fi

if [ "$MODE" = train ]; then
    setup_env || exit 5
    nvidia-smi -L | tee "$OUT/train.log"
    python3 -m experiments.derive_dataset --data datasets/paper --split train --limit ${NTRAIN:-3000} \
        --workers 16 --no-progress >"$W/derive_train.log" 2>&1
    echo "[$(($(date +%s) - T0)) s] derived $(ls datasets/paper/derived/train | wc -l)" | tee -a "$OUT/train.log"
    python3 -m experiments.train_stage3 --preset paper --out "$W/run" --workers 15 \
        --time-budget ${TRAIN_S:-360} --pretrain-steps ${PRETRAIN:-6000} --rounds ${ROUNDS:-8} \
        --no-progress >"$W/train_stage3.log" 2>&1
    echo "[$(($(date +%s) - T0)) s] trained: $?" | tee -a "$OUT/train.log"
    cd "$W" || exit 1
    tar -czf "$OUT/stage3.tgz" --exclude=run/buffer.npz --exclude=run/train_state.msgpack \
        run derive_train.log train_stage3.log
    tail -3 run/rounds.jsonl | cut -c1-400
    exit 0
fi
echo "unknown mode $MODE: train or curve" >&2
exit 2
