#!/usr/bin/env bash
# Chain part "nce" (docs/paths.md): train the neural collision estimator (and the HCE
# normal net) for the planner, resuming across calls of the device chain.
#
#   bash scripts/chain/nce.sh BUDGET_S OUT_TGZ        # e.g. 500 /tmp/chain/out/nce_1.tgz
#   SKIP_INSTALL=1 CHAIN_TINY=1 bash scripts/chain/nce.sh 120 /tmp/x.tgz   # local test
#
# One call (all under BUDGET_S wall clock, startup included):
# 1. derive (CPU, CHAIN_WORKERS processes, train_collision's own derive, resumable) the
#    held-out pairs' files (N_TEST, first), then in the background as many training-split
#    pairs as the call allows (all of them eventually): clouds (reused from the chain's
#    /tmp/chain/ds/derived/train/ where derive_dataset has written them), the dataset's
#    collision labels, stable poses, and the near-contact poses labelled on the full meshes
#    (train_collision.near_contact_poses). State: /tmp/chain/nce/derived/.
# 2. from DERIVE_FRACTION of the budget on (first call; RESUME_WAIT_S on later ones), train on
#    the GPU on every pair derived by then (--existing-only), resuming from the weights of the
#    previous call (/tmp/chain/nce/run/): the NCE with dataset labels + far free poses + stable
#    poses free + near-contact mesh labels; the HCE normal net; the NCE threshold chosen on
#    validation pairs of the training split (pair_index % 20 == 0, never trained on) so that
#    95 % of their stable poses pass; metrics on held-out labels (accuracy / precision /
#    recall), held-out goal-pass rate and near-contact metrics.
# 3. OUT_TGZ (< 1 MiB): weights/{nce,hce_normals}/, weights/hce_true_normals.json,
#    weights/metrics.json, summary.json, logs/. Unpack: tar -xzf OUT_TGZ -C DIR, then
#    eval_paths --weights DIR/weights.
# Knobs (env): N_TEST (150 held-out pairs), N_TRAIN (20000: all), PRESET (fast), BATCH (256),
# DERIVE_FRACTION (0.4), RESUME_WAIT_S (60), NORMALS_S (30), NCE_MAX_S (no cap), EVAL_RESERVE_S
# (110: when training may start at the latest), COMPILE_RESERVE_S (60) and POST_RESERVE_S (90):
# train_collision --deadline (end of the call - 15 s) gives the NCE what is left after loading
# the pairs (measured: 7,984 pairs took minutes beside 15 derive workers on the first device
# attempt, which overran), one compilation and the reserve for the threshold, held-out
# metrics, normal net and HCEs; CHAIN_WORKERS (3), CHAIN_DS (/tmp/chain/ds).
# CHAIN_TINY=1: tiny preset, 4 held-out + 40 training pairs, NCE 20 s, reserve 40 s.
# GPU memory: XLA_PYTHON_CLIENT_MEM_FRACTION 0.12 unless set.
# NCE_ARGS / BASE_ARGS: more train_collision flags (e.g. "--val-curve-every 1000").
set -uo pipefail
BUDGET=${1:?usage: nce.sh BUDGET_S OUT_TGZ}
OUT_TGZ=${2:?usage: nce.sh BUDGET_S OUT_TGZ}
T0=$(date +%s)
STATE=${CHAIN_STATE:-/tmp/chain/nce}  # local tests: a private CHAIN_STATE
DS=${CHAIN_DS:-/tmp/chain/ds}
WORKERS=${CHAIN_WORKERS:-3}
mkdir -p "$STATE/logs" "$STATE/run"
CALL=$(($(ls "$STATE/logs" | grep -c '^call_') + 1))
LOG=$STATE/logs/call_$CALL.log
elapsed() { echo $(($(date +%s) - T0)); }
left() { echo $((BUDGET - $(elapsed))); }
log() { echo "[nce call $CALL, $(elapsed) s] $*" | tee -a "$LOG"; }

if [ -n "${CHAIN_TINY:-}" ]; then
    N_TEST=${N_TEST:-4} N_TRAIN=${N_TRAIN:-40} PRESET=${PRESET:-tiny} BATCH=${BATCH:-16}
    NORMALS_S=${NORMALS_S:-3} EVAL_RESERVE_S=${EVAL_RESERVE_S:-40} RESUME_WAIT_S=${RESUME_WAIT_S:-5}
    EVAL_LABELS=2000 THRESHOLD_LABELS=2000 NORMAL_BATCH=4 NCE_MAX_S=${NCE_MAX_S:-20}
    COMPILE_RESERVE_S=${COMPILE_RESERVE_S:-20} POST_RESERVE_S=${POST_RESERVE_S:-30}
else
    N_TEST=${N_TEST:-150} N_TRAIN=${N_TRAIN:-20000} PRESET=${PRESET:-fast} BATCH=${BATCH:-256}
    NORMALS_S=${NORMALS_S:-30} EVAL_RESERVE_S=${EVAL_RESERVE_S:-110} RESUME_WAIT_S=${RESUME_WAIT_S:-60}
    EVAL_LABELS=50000 THRESHOLD_LABELS=20000 NORMAL_BATCH=32 NCE_MAX_S=${NCE_MAX_S:-100000}
    COMPILE_RESERVE_S=${COMPILE_RESERVE_S:-60} POST_RESERVE_S=${POST_RESERVE_S:-90}
fi
DERIVE_FRACTION=${DERIVE_FRACTION:-0.4}
export PYTHONPATH=${PYTHONPATH:-/tmp/site:$PWD} PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
export XLA_PYTHON_CLIENT_MEM_FRACTION=${XLA_PYTHON_CLIENT_MEM_FRACTION:-0.12}  # per process
PY=${PYTHON:-python3}  # the chain's image python; SKIP_INSTALL=1 (local test): the venv's
if [ -n "${SKIP_INSTALL:-}" ] && [ -z "${PYTHON:-}" ] && [ -x .venv/bin/python ]; then PY=.venv/bin/python; fi
log "budget ${BUDGET} s, ${WORKERS} workers, dataset $DS ($(ls "$DS/derived/train" 2>/dev/null | wc -l) derive_dataset train files), preset $PRESET"
if [ ! -f "$DS/recipe.json" ]; then
    log "error: $DS/recipe.json missing (the chain's dataset)"
    exit 3
fi

COMMON=(--data "$DS" --derived-dir "$STATE/derived" --out "$STATE/run" --preset "$PRESET"
    --test-pairs "$N_TEST" --train-pairs "$N_TRAIN" --no-progress)

# 1. one background derive (resumable; held-out pairs first, then training pairs) until 15 s
#    before the end of the call
timeout -k 5 $(($(left) - 15)) "$PY" -m experiments.train_collision "${COMMON[@]}" \
    --derive-only --workers "$WORKERS" >>"$STATE/logs/derive_$CALL.log" 2>&1 &
DERIVE_PID=$!

# 2. wait for training pairs, then train on what is there
if [ -f "$STATE/run/nce/config.json" ]; then
    START_AT=$RESUME_WAIT_S
    RESUME=--resume
else
    START_AT=$(awk "BEGIN {print int($BUDGET * $DERIVE_FRACTION)}")
    RESUME=
fi
LATEST=$((BUDGET - EVAL_RESERVE_S - NORMALS_S - 20))  # train no later than this
n_test() { ls "$STATE/derived/test" 2>/dev/null | wc -l; }
while kill -0 "$DERIVE_PID" 2>/dev/null && [ "$(elapsed)" -lt "$LATEST" ] &&
    { [ "$(elapsed)" -lt "$START_AT" ] || [ "$(n_test)" -lt "$N_TEST" ]; }; do sleep 2; done
N_HAVE=$(ls "$STATE/derived/train" 2>/dev/null | wc -l)
log "held-out pairs derived: $(n_test) of $N_TEST"
# train_collision sizes the NCE's time itself (--deadline): what is left after loading the
# pairs (measured), compilation (COMPILE_RESERVE_S) and what follows (POST_RESERVE_S + normals)
DEADLINE=$((T0 + BUDGET - 15))
NCE_S=$(($(left) - EVAL_RESERVE_S - NORMALS_S))  # an upper bound; the deadline decides
[ "$NCE_S" -gt "$NCE_MAX_S" ] && NCE_S=$NCE_MAX_S
TIMING=(--deadline "$DEADLINE" --compile-reserve-s "$COMPILE_RESERVE_S" --post-reserve-s "$POST_RESERVE_S")
log "training on up to $N_HAVE derived training pairs: NCE at most ${NCE_S} s (deadline in $((DEADLINE - $(date +%s))) s), normals ${NORMALS_S} s ${RESUME:+(resumed)}"
STATUS=0
if [ "$NCE_S" -lt 5 ]; then
    log "error: no time left to train (budget ${BUDGET} s too small)"
    STATUS=4
else
    timeout -k 5 $(($(left) - 12)) "$PY" -m experiments.train_collision "${COMMON[@]}" \
        --existing-only $RESUME --batch "$BATCH" --normal-batch "$NORMAL_BATCH" \
        --time-budget "nce=$NCE_S,normals=$NORMALS_S" "${TIMING[@]}" --eval-labels "$EVAL_LABELS" \
        --threshold-labels "$THRESHOLD_LABELS" ${NCE_ARGS:-} ${BASE_ARGS:-} >"$STATE/logs/train_$CALL.log" 2>&1
    STATUS=$?
    grep -E "^pairs:|^held-out" "$STATE/logs/train_$CALL.log" | tee -a "$LOG"
    [ "$STATUS" -eq 0 ] || log "error: train_collision exited $STATUS (see logs/train_$CALL.log)"
fi
kill "$DERIVE_PID" 2>/dev/null
wait "$DERIVE_PID" 2>/dev/null
log "derived now: $(ls "$STATE/derived/train" | wc -l) training, $(ls "$STATE/derived/test" | wc -l) held-out pairs"

# 3. the tarball
PACK=$(mktemp -d)
mkdir -p "$PACK/weights" "$PACK/logs"
cp -r "$STATE/run/." "$PACK/weights/" 2>/dev/null
cp "$STATE"/logs/*.log "$PACK/logs/" 2>/dev/null
"$PY" - "$STATE" "$PACK/summary.json" "$CALL" "$STATUS" "$(elapsed)" <<'EOF' >>"$LOG" 2>&1
import json, os, sys
state, out, call, status, seconds = sys.argv[1:]
m = {}
if os.path.exists(f"{state}/run/metrics.json"):
    m = json.load(open(f"{state}/run/metrics.json"))
near = m.get("held_out_near", {}).get("nce", {})
summary = dict(
    part="nce", call=int(call), status=int(status), seconds=int(seconds),
    derived_train=len(os.listdir(f"{state}/derived/train")) if os.path.isdir(f"{state}/derived/train") else 0,
    derived_test=len(os.listdir(f"{state}/derived/test")) if os.path.isdir(f"{state}/derived/test") else 0,
    train_pairs=m.get("train_pairs"), validation_pairs=m.get("validation_pairs"),
    nce_steps_this_call=m.get("nce", {}).get("steps"), nce_threshold=m.get("nce_threshold"),
    held_out_labels={k: {x: v.get(x) for x in ("accuracy", "precision", "recall", "balanced_accuracy", "n")}
                     for k, v in m.get("held_out", {}).items()},
    goal_pass=near.get("goal_pass"), near_contact=near.get("near"),
)
json.dump(summary, open(out, "w"), indent=2)
print(json.dumps(summary))
EOF
cp "$LOG" "$PACK/logs/" 2>/dev/null
mkdir -p "$(dirname "$OUT_TGZ")"
tar -czf "$OUT_TGZ" -C "$PACK" . && rm -rf "$PACK"
log "wrote $OUT_TGZ ($(du -k "$OUT_TGZ" | cut -f1) KiB); status $STATUS"
exit "$STATUS"
