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
#   eval      derive the held-out pairs of results/hanging_success.pairs.jsonl, eval_stage3 on
#             all of them with VALUE (default weights/value), bench_stage3
#   curve     the refinement-learning curve + CEM_ROUNDS-round CEM on a balanced subset
#   variants  eval again (with the separated answer) + K = 10 proposals on a balanced subset
# Knobs: NTRAIN (3000), TRAIN_S (360), PRETRAIN (6000), ROUNDS (8), VALUE (the V weights folder of
# eval / curve / variants: weights/value), LABEL, CEM_ROUNDS, PER_CAT.
# V on ALL training pairs with hard-negative rounds (weights/value) is the chain part
# scripts/chain/stage3.sh (2-3 calls, resumable), not a mode here.
set -uo pipefail
MODE=${1:?usage: device_stage3.sh train|eval|curve|variants}
OUT=${OUT:-/tmp/out}
W=/tmp/s3
T0=$(date +%s)
mkdir -p "$OUT" "$W"
setup_env() {  # the carried wheels into /tmp/site; this tree on the path
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site \
        .whl_min/*.whl .whl_train/*.whl || return 5
    export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
}

if [ "$MODE" = eval ]; then
    # one call, foreground: derive the held-out pairs, evaluate the committed V
    # (VALUE, default weights/value) on all of them, benchmark the pipeline
    setup_env || exit 5
    V=${VALUE:-weights/value}
    nvidia-smi -L | tee "$OUT/eval.log"
    python3 -m experiments.derive_dataset --data datasets/paper --split test \
        --pairs-from results/hanging_success.pairs.jsonl --workers 16 --no-progress >"$OUT/derive_test.log" 2>&1
    echo "[$(($(date +%s) - T0)) s] derived $(ls datasets/paper/derived/test | wc -l)" | tee -a "$OUT/eval.log"
    timeout ${EVAL_S:-420} python3 -m experiments.eval_stage3 --value "$V" \
        --pairs-from results/hanging_success.pairs.jsonl --workers 15 --batch 16 \
        --out "$OUT/hanging_success_stage3.json" --label "${LABEL:-the 1,814 held-out pairs}" \
        --no-progress 2>&1 | tail -40 | tee -a "$OUT/eval.log"
    echo "[$(($(date +%s) - T0)) s] evaluated" | tee -a "$OUT/eval.log"
    timeout $((570 - $(date +%s) + T0)) python3 -m experiments.bench_stage3 --value "$V" \
        --out "$OUT/bench_stage3.json" 2>&1 | tail -5 | tee -a "$OUT/eval.log"
    gzip -f "$OUT"/*.pairs.jsonl 2>/dev/null
    exit 0
fi

if [ "$MODE" = variants ]; then
    # one call: the held-out evaluation again (now also the separated answer), then K = 10
    # proposals on a balanced subset (more proposals = a wider search)
    setup_env || exit 5
    nvidia-smi -L | tee "$OUT/variants.log"
    python3 -m experiments.derive_dataset --data datasets/paper --split test \
        --pairs-from results/hanging_success.pairs.jsonl --workers 16 --no-progress >/dev/null 2>&1
    timeout 300 python3 -m experiments.eval_stage3 --value "${VALUE:-weights/value}" --pairs-from results/hanging_success.pairs.jsonl \
        --workers 15 --batch 16 --out "$OUT/hanging_success_stage3.json" \
        --label "the 1,814 held-out pairs" --no-progress 2>&1 | tail -9 | tee -a "$OUT/variants.log"
    echo "[$(($(date +%s) - T0)) s] K=5 done" | tee -a "$OUT/variants.log"
    timeout $((575 - $(date +%s) + T0)) python3 -m experiments.eval_stage3 --value "${VALUE:-weights/value}" \
        --pairs-from results/hanging_success.pairs.jsonl --per-category 60 --proposals 10 \
        --workers 15 --batch 8 --out "$OUT/hanging_success_k10.json" \
        --label "K = 10 proposals, balanced subset" --no-progress 2>&1 | tail -9 | tee -a "$OUT/variants.log"
    echo "[$(($(date +%s) - T0)) s] done" | tee -a "$OUT/variants.log"
    gzip -f "$OUT"/*.pairs.jsonl 2>/dev/null
    exit 0
fi

if [ "$MODE" = curve ]; then
    # one call: the refinement-learning curve (100 training pairs, 10,000 steps, Stage-2 vs
    # uniform start), then CEM_ROUNDS-round CEM on a balanced held-out subset (a variant)
    setup_env || exit 5
    nvidia-smi -L | tee "$OUT/curve.log"
    python3 -m experiments.derive_dataset --data datasets/paper --split train --limit 400 \
        --workers 16 --no-progress >/dev/null 2>&1
    (python3 -m experiments.derive_dataset --data datasets/paper --split test \
        --pairs-from results/hanging_success.pairs.jsonl --workers 6 --no-progress >/dev/null 2>&1; touch /tmp/test_derived) &
    timeout ${CURVE_S:-300} python3 -m experiments.refinement_learning --workers 10 \
        --out "$OUT/refinement_learning.json" --no-progress 2>&1 | tail -3 | tee -a "$OUT/curve.log"
    echo "[$(($(date +%s) - T0)) s] curve" | tee -a "$OUT/curve.log"
    while [ ! -e /tmp/test_derived ]; do sleep 2; done
    timeout $((575 - $(date +%s) + T0)) python3 -m experiments.eval_stage3 --value "${VALUE:-weights/value}" \
        --pairs-from results/hanging_success.pairs.jsonl --per-category ${PER_CAT:-60} \
        --rounds ${CEM_ROUNDS:-2} --workers 15 --batch 16 --out "$OUT/hanging_success_cem2.json" \
        --label "CEM ${CEM_ROUNDS:-2} rounds, balanced subset" --no-progress 2>&1 | tail -12 | tee -a "$OUT/curve.log"
    echo "[$(($(date +%s) - T0)) s] done" | tee -a "$OUT/curve.log"
    gzip -f "$OUT"/*.pairs.jsonl 2>/dev/null
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
echo "unknown mode $MODE: train, eval, curve or variants" >&2
exit 2
