#!/usr/bin/env bash
# Stage 3 on one GPU machine, spread over consecutive device calls (each <= 10 min) while the
# machine stays warm: the job runs in its own process session (setsid) and survives the call
# that started it; every call waits for it up to WAIT_S and brings back what exists so far.
#
#   call 1: run(carry=[".whl_min", ".whl_train"], timeout_s=600,
#               command="bash scripts/device_stage3.sh start")
#   call 2+: run(carry=[".whl_min", ".whl_train"], timeout_s=600,
#               command="bash scripts/device_stage3.sh wait")     (issue within 30 s)
#   (measured: the 30-s warm window is easily missed, and a missed one starts a bare machine
#   that has lost the job; the whole train job fits one call: docs/device_runs.md)
#   eval:   run(carry=[".whl_min", ".whl_train"], timeout_s=600,
#               command="bash scripts/device_stage3.sh eval")      (one call, foreground)
#
# The job: derive NTRAIN training pairs (round robin over categories) and the held-out pairs
# of results/hanging_success.pairs.jsonl on all cores; train V (experiments.train_stage3,
# preset paper, TRAIN_S budget: seed buffer, pretrain, RL rounds); evaluate Stages 1, 1+2,
# 1+3, all on the held-out pairs (EVAL_PER_CAT per category first, then all of them if time
# is left); benchmark the pipeline. Results come back as $OUT/stage3.tgz + logs.
# Knobs: NTRAIN (3000), TRAIN_S (780), PRETRAIN (6000), ROUNDS (8), EVAL_PER_CAT (50).
set -uo pipefail
MODE=${1:-wait}
OUT=${OUT:-/tmp/out}
W=/tmp/s3
WAIT_S=${WAIT_S:-560}
T0=$(date +%s)
mkdir -p "$OUT" "$W"
setup_env() {  # the carried wheels into /tmp/site; this tree on the path
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site \
        .whl_min/*.whl .whl_train/*.whl || return 5
    export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
}

if [ "$MODE" = eval ]; then
    # one call, foreground: derive the held-out pairs, evaluate the committed V
    # (VALUE, default weights/value_small_paper) on all of them, benchmark the pipeline
    setup_env || exit 5
    V=${VALUE:-weights/value_small_paper}
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
    timeout 300 python3 -m experiments.eval_stage3 --pairs-from results/hanging_success.pairs.jsonl \
        --workers 15 --batch 16 --out "$OUT/hanging_success_stage3.json" \
        --label "the 1,814 held-out pairs" --no-progress 2>&1 | tail -9 | tee -a "$OUT/variants.log"
    echo "[$(($(date +%s) - T0)) s] K=5 done" | tee -a "$OUT/variants.log"
    timeout $((575 - $(date +%s) + T0)) python3 -m experiments.eval_stage3 \
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
    timeout $((575 - $(date +%s) + T0)) python3 -m experiments.eval_stage3 \
        --pairs-from results/hanging_success.pairs.jsonl --per-category ${PER_CAT:-60} \
        --rounds ${CEM_ROUNDS:-2} --workers 15 --batch 16 --out "$OUT/hanging_success_cem2.json" \
        --label "CEM ${CEM_ROUNDS:-2} rounds, balanced subset" --no-progress 2>&1 | tail -12 | tee -a "$OUT/curve.log"
    echo "[$(($(date +%s) - T0)) s] done" | tee -a "$OUT/curve.log"
    gzip -f "$OUT"/*.pairs.jsonl 2>/dev/null
    exit 0
fi

if [ "$MODE" = start ]; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site \
        .whl_min/*.whl .whl_train/*.whl || exit 5
    rm -rf /tmp/s3repo && cp -r "$PWD" /tmp/s3repo  # the job's own copy of the tree
    cat >"$W/job.sh" <<EOF
set -uo pipefail
cd /tmp/s3repo
export PYTHONPATH=/tmp/site:/tmp/s3repo PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
log() { echo "[\$((\$(date +%s) - $T0)) s] \$*" >>$W/job.log; }
nvidia-smi -L >>$W/job.log
log "derive"
python3 -m experiments.derive_dataset --data datasets/paper --split test \
    --pairs-from results/hanging_success.pairs.jsonl --workers 16 --no-progress >$W/derive_test.log 2>&1
log "derived test: \$(ls datasets/paper/derived/test | wc -l)"
python3 -m experiments.derive_dataset --data datasets/paper --split train --limit ${NTRAIN:-3000} \
    --workers 16 --no-progress >$W/derive_train.log 2>&1
log "derived train: \$(ls datasets/paper/derived/train | wc -l)"
python3 -m experiments.train_stage3 --preset paper --out $W/run --workers 15 \
    --time-budget ${TRAIN_S:-780} --pretrain-steps ${PRETRAIN:-6000} --rounds ${ROUNDS:-8} \
    --no-progress >$W/train.log 2>&1
log "trained: \$?"
python3 -m experiments.eval_stage3 --value $W/run/value --pairs-from results/hanging_success.pairs.jsonl \
    --per-category ${EVAL_PER_CAT:-50} --workers 15 --batch 16 --out $W/eval_subset.json \
    --label "balanced subset of the 1,814 held-out pairs" --no-progress >$W/eval_subset.log 2>&1
log "eval subset: \$?"
python3 -m experiments.bench_stage3 --value $W/run/value --out $W/bench_stage3.json >$W/bench.log 2>&1
log "bench: \$?"
python3 -m experiments.eval_stage3 --value $W/run/value --pairs-from results/hanging_success.pairs.jsonl \
    --workers 15 --batch 16 --out $W/eval_all.json --label "the 1,814 held-out pairs" \
    --no-progress >$W/eval_all.log 2>&1
log "eval all: \$?"
touch $W/done
EOF
    setsid bash "$W/job.sh" >"$W/job.out" 2>&1 </dev/null &
    echo "started job in /tmp/s3repo"
fi

# wait for the job (or WAIT_S), then bring back everything small
while [ ! -e "$W/done" ] && [ $(($(date +%s) - T0)) -lt "$WAIT_S" ]; do
    sleep 10
done
cd "$W" || exit 1
ls run 2>/dev/null
tar -czf "$OUT/stage3.tgz" --exclude=run/buffer.npz --exclude=run/train_state.msgpack \
    $(ls -d run *.json *.jsonl *.log 2>/dev/null) 2>/dev/null
cp job.log "$OUT/" 2>/dev/null
tail -5 run/rounds.jsonl 2>/dev/null | cut -c1-400
tail -3 run/metrics.jsonl 2>/dev/null | cut -c1-400
cat job.log
[ -e done ] && echo "JOB DONE" || echo "job still running"
