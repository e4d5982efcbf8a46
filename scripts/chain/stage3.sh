#!/usr/bin/env bash
# Chain part "stage3" (docs/stage3.md): train the Stage-3 value function V on ALL
# derived training pairs with hard-negative RL rounds, resuming across calls of the device chain.
#
#   bash scripts/chain/stage3.sh BUDGET_S OUT_TGZ        # e.g. 520 /tmp/chain/out/stage3_1.tgz
#   SKIP_INSTALL=1 CHAIN_TINY=1 bash scripts/chain/stage3.sh 120 /tmp/x.tgz   # local test
#
# One call (all under BUDGET_S wall clock, startup included) runs
# `experiments.train_stage3 --preset hardneg` in /tmp/chain/stage3/run/ (resumed if present):
# 1. waits for MIN_PAIRS derived training pairs in $CHAIN_DS/derived/train (the chain's
#    background derive may still be writing them), appends every derived pair to the job's
#    bank (slots never move; bank.npz) and seeds the new ones in chunks: their stable poses
#    (reward 1), 8 + 8 perturbations inside CEM's box and +-5 mm / 0.1 rad, the K = 5
#    Stage-1 and Stage-2 proposals of WHERE (weights/stage12), all labelled by
#    sim.kernels.stability under protocol_stability in CHAIN_WORKERS processes;
# 2. pretrains V (6,000 steps, once);
# 3. hard-negative RL rounds until the budget: CEM on the current V from the Stage-2
#    proposals of 256 random fit pairs; the answers, the 8 best-scored members of every final
#    population (V's false positives among them) and a perturbed copy of each answer are
#    labelled by the physics and added; V trains 400 steps with a quarter of each batch from
#    those hard cases; every 3 rounds the newly derived pairs are ingested and seeded, and the
#    same is measured on 128 validation pairs (objects of a fixed 10 % of the training objects,
#    never trained on): success of V's pick, of any refined candidate, V's precision on them.
# 4. OUT_TGZ (~5 MiB): value/ (config.json + params.msgpack: the weights for
#    omnihang_jax.where.WhereConfig.value), metrics.jsonl, rounds.jsonl,
#    curves.png, split.json, state.json, config.json, job summary.json, logs/, and summary.json
#    (this call). Unpack: mkdir -p DIR && tar -xzf OUT_TGZ -C DIR; the weights are DIR/value.
# Knobs (env): PRESET (hardneg; CHAIN_TINY=1: hardneg_tiny), MIN_PAIRS (200), RESERVE_S (40:
# startup + packing outside the job's own budget), INIT_VALUE (start V from a value/ folder),
# WHERE (weights/stage12), EXTRA (more train_stage3 flags), CHAIN_WORKERS (3),
# CHAIN_DS (/tmp/chain/ds), STAGE3_STATE (/tmp/chain/stage3). GPU memory: XLA_PYTHON_CLIENT_MEM_FRACTION 0.22 unless set.
set -uo pipefail
BUDGET=${1:?usage: stage3.sh BUDGET_S OUT_TGZ}
OUT_TGZ=${2:?usage: stage3.sh BUDGET_S OUT_TGZ}
T0=$(date +%s)
STATE=${STAGE3_STATE:-/tmp/chain/stage3}  # local tests: elsewhere (the chain test clears /tmp/chain)
DS=${CHAIN_DS:-/tmp/chain/ds}
WORKERS=${CHAIN_WORKERS:-3}
mkdir -p "$STATE/logs" "$STATE/run"
CALL=$(($(ls "$STATE/logs" | grep -c '^call_') + 1))
LOG=$STATE/logs/call_$CALL.log
elapsed() { echo $(($(date +%s) - T0)); }
left() { echo $((BUDGET - $(elapsed))); }
log() { echo "[stage3 call $CALL, $(elapsed) s] $*" | tee -a "$LOG"; }

if [ -n "${CHAIN_TINY:-}" ]; then
    PRESET=${PRESET:-hardneg_tiny} MIN_PAIRS=${MIN_PAIRS:-4} RESERVE_S=${RESERVE_S:-25}
else
    PRESET=${PRESET:-hardneg} MIN_PAIRS=${MIN_PAIRS:-200} RESERVE_S=${RESERVE_S:-40}
fi
WHERE=${WHERE:-weights/stage12}
export PYTHONPATH=${PYTHONPATH:-/tmp/site:$PWD} PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
export XLA_PYTHON_CLIENT_MEM_FRACTION=${XLA_PYTHON_CLIENT_MEM_FRACTION:-0.22}
PY=${PYTHON:-python3}  # the chain's image python; SKIP_INSTALL=1 (local test): the venv's
if [ -n "${SKIP_INSTALL:-}" ] && [ -z "${PYTHON:-}" ] && [ -x .venv/bin/python ]; then PY=.venv/bin/python; fi
log "budget ${BUDGET} s, ${WORKERS} workers, dataset $DS ($(ls "$DS/derived/train" 2>/dev/null | wc -l) derived training files), preset $PRESET, job $STATE/run ($(cat "$STATE/run/state.json" 2>/dev/null | tr -d ' \n' || echo new))"
STATUS=0
if [ ! -f "$DS/recipe.json" ]; then
    log "error: $DS/recipe.json missing (the chain's dataset)"
    STATUS=3
elif [ ! -f "$WHERE/stage1/config.json" ] && [ ! -d "$WHERE/stage1" ]; then
    log "error: Stage-1/2 weights $WHERE missing"
    STATUS=3
fi

JOB_S=$(($(left) - RESERVE_S))
if [ "$STATUS" -eq 0 ] && [ "$JOB_S" -lt 30 ]; then
    log "error: budget ${BUDGET} s leaves ${JOB_S} s for the job"
    STATUS=4
fi
if [ "$STATUS" -eq 0 ]; then
    INIT=()
    [ -n "${INIT_VALUE:-}" ] && INIT=(--init-value "$INIT_VALUE")
    # the job stops its phases cleanly by its own budget (state saved after every seed chunk
    # and round); the timeout is only a guard, 15 s before the end of the call
    timeout -k 5 $(($(left) - 15)) "$PY" -m experiments.train_stage3 --preset "$PRESET" \
        --out "$STATE/run" --data "$DS" --weights "$WHERE" --workers "$WORKERS" \
        --time-budget "$JOB_S" --min-pairs "$MIN_PAIRS" "${INIT[@]}" ${EXTRA:-} --no-progress \
        >"$STATE/logs/train_$CALL.log" 2>&1
    STATUS=$?
    if [ "$STATUS" -eq 124 ] || [ "$STATUS" -eq 137 ]; then
        log "warning: train_stage3 ran into the guard timeout; the state of the last seed chunk / round is kept and the next call resumes"
        # progress was saved (state.json): not a failure, the next call goes on from there
        [ -f "$STATE/run/state.json" ] && STATUS=0
    elif [ "$STATUS" -ne 0 ]; then
        log "error: train_stage3 exited $STATUS (see logs/train_$CALL.log):"
        tail -5 "$STATE/logs/train_$CALL.log" | tee -a "$LOG"
    fi
    grep -h '"round"' "$STATE/run/rounds.jsonl" 2>/dev/null | tail -2 | cut -c1-400 | tee -a "$LOG"
fi

# the tarball: weights + record, not the buffer / bank / train state (those stay for resuming)
PACK=$(mktemp -d)
mkdir -p "$PACK/logs"
if [ -d "$STATE/run" ]; then
    (cd "$STATE/run" && cp -r value config.json state.json summary.json split.json metrics.jsonl \
        rounds.jsonl curves.png "$PACK/" 2>/dev/null)
fi
cp "$STATE"/logs/*.log "$PACK/logs/" 2>/dev/null
"$PY" - "$STATE" "$PACK/summary.json" "$CALL" "$STATUS" "$(elapsed)" "$DS" <<'EOF' >>"$LOG" 2>&1
import json, os, sys
state, out, call, status, seconds, ds = sys.argv[1:]
run = f"{state}/run"
def rows(name):
    p = f"{run}/{name}"
    return [json.loads(x) for x in open(p).read().splitlines() if x.strip()] if os.path.exists(p) else []
rounds = [r for r in rows("rounds.jsonl") if "round" in r]
val = [r for r in rounds if "val_all_stages_success" in r]
st = json.load(open(f"{run}/state.json")) if os.path.exists(f"{run}/state.json") else {}
job = json.load(open(f"{run}/summary.json")) if os.path.exists(f"{run}/summary.json") else {}
d = f"{ds}/derived/train"
keys = ("round", "pairs", "chosen_success", "any_refined_success", "top_success", "top_precision",
        "val_all_stages_success", "val_any_refined_success", "val_top_precision", "val_stage1_2_success",
        "val_balanced_accuracy", "val_hard_precision", "val_hard_recall", "val_hard_balanced_accuracy")
summary = dict(
    part="stage3", call=int(call), status=int(status), seconds=int(seconds),
    derived_train=len([f for f in os.listdir(d) if f.endswith(".npz") and not f.startswith(".")]) if os.path.isdir(d) else 0,
    bank_pairs=job.get("pairs"), state=st, buffer=job.get("buffer", {}).get("transitions"),
    weights_exported=os.path.exists(f"{run}/value/params.msgpack"),
    v_steps=json.load(open(f"{run}/value/config.json")).get("step") if os.path.exists(f"{run}/value/config.json") else 0,
    last_round={k: rounds[-1].get(k) for k in keys} if rounds else None,
    last_val={k: val[-1].get(k) for k in keys} if val else None,
)
json.dump(summary, open(out, "w"), indent=2)
print(json.dumps(summary))
EOF
cp "$LOG" "$PACK/logs/" 2>/dev/null
mkdir -p "$(dirname "$OUT_TGZ")"
tar -czf "$OUT_TGZ" -C "$PACK" . && rm -rf "$PACK"
log "wrote $OUT_TGZ ($(du -k "$OUT_TGZ" | cut -f1) KiB); status $STATUS"
exit "$STATUS"
