#!/usr/bin/env bash
# The eighth session's GPU job (issues 14 and 12): every training pair, Stage 1 fine-tuned on
# all of them and V's hard-negative rounds side by side, then the held-out evaluation.
#
#   bash scripts/device_slim.sh out
#   run(carry=[".whl_min", ".whl_train"], timeout_s=600, command="bash scripts/device_full.sh train")
#   run(..., command="bash scripts/device_full.sh eval")     # next call (same machine if warm)
#   bash scripts/device_slim.sh in
#
# CALL
#   train  install; derive every training pair clouds-only at half the camera resolution
#          (`derive_dataset --clouds-only --camera-scale 0.5`, ~3x less CPU than a full derive;
#          the held-out pairs keep the recipe's 640 x 480) on 16 workers for at most DERIVE_S
#          (240 s); pack; then side by side until END_S:
#          - Stage 1 (small preset) fine-tuned from INIT1 (weights/where_small_paper) on all
#            packed pairs minus the validation objects: batch BATCH1 (128), lr LR1 (5e-4) with
#            warm-up 300 and cosine over STEPS1 (30000, spread over calls: a warm next call
#            resumes it), validation every 500 steps;
#          - the Stage-3 part (scripts/chain/stage3.sh, hard-negative V, S3_W = 11 workers,
#            V from INIT_VALUE (default VALUE, stage3.CEM_VALUE), 1,000 pretraining steps, 512 pairs a round, at
#            most S3_PAIRS = 4000 pairs seeded) on the same clouds;
#          - the held-out pairs derived (3 workers) for the eval call.
#   eval   derive the held-out pairs if absent; eval_stage3 on all 1,794 of them (the 1,814 of
#          results/hanging_success.pairs.jsonl that keep stable poses under labels v3) for
#          WHERE_W (default: the train call's best export) with the committed V (EVAL_ARGS: more
#          eval_stage3 flags, e.g. "--stage2-clearance 0.012"; EVAL_TAG names the outputs), the
#          Stage-3 answer rule chosen on validation objects applied to its records
#          (experiments.rerank_stage3 -> TAG_rerank.json), then with the train call's new V.
#   val    the 396 validation-object pairs (results/validation_pairs.jsonl; derived if absent)
#          through eval_stage3 with WHERE_W / VALUE (VAL_ARGS: more flags), or with each of
#          VAL_WS="NAME=WEIGHTS ..." in turn: Stage-1 variants are chosen on these figures, and
#          experiments.rerank_stage3 chooses the answer rule on their records.
#   smooth experiments.smooth_stage3: the answer by V averaged around each refined candidate,
#          its width chosen on validation-object records, applied to held-out records (SMOOTH_VAL,
#          SMOOTH_HELD, SMOOTH_ARGS); derives both pair sets if absent.
#   valeval (issue 12) the validation objects with every candidate ranking network recorded
#          (RANK_CANDIDATES), the set chosen there (ensemble_stage3 --from-records), then the
#          held-out eval with it; VAL_ARGS / EVAL_ARGS as for val / eval (e.g. --proposals 10);
#          HELD_IF_ABOVE=X runs the held-out part only when the validation figure beats X.
#   bench  bench_stage3: Stages 1-3 latency at batch 1 / 16 / 256, the answer pipeline
#          (stage3.ANSWER_PIPELINE) and the paper's side by side (~3 min with compilation).
# S3_ONLY=1 (train): derive the clouds (skipped when there), no pack, no Stage 1: the Stage-3
# part alone on S3_W (15) workers, every training pair (S3_PAIRS, 0 = all), V from INIT_VALUE
# (weights/value_s16_hardneg = stage3.CEM_VALUE), S3_PRETRAIN (2000) steps, S3_EXTRA more train_stage3 flags (e.g.
# "--round-start alternate"); a warm next S3_ONLY call resumes the job (/tmp/full/stage3/run).
# eval: VALUE (the V of the first evaluation; default the committed one), NO_NEWV=1 skips the
# second evaluation with the train call's V.
# S1_VARIANTS="6d 6dorig" (INIT1=none): the small and the original preset (the paper's encoder,
# 4,096 points) side by side, both with the 6-D head (issue 14's preset comparison).
# INIT1=none trains Stage 1 from scratch; S1_ARGS adds train_where flags, e.g. S1_ARGS="--stage1
# rotation=6d --stage1 set_loss_mean=true" (a changed head needs INIT1=none).
# VIEWS=2: also derive every pair's next candidate view (`--view 1`, ~100 s more) and train on
# both (augmentation with real renders; DERIVE_S is then the budget per view). PACK_ONLY=1 stops
# after the pack; SKIP_PACK=1 (next call, warm machine) trains on that pack as it is.
# Back in $OUT: full.log, where.tgz (stage-1 best + latest exports, the resumable checkpoint,
# metrics, validation curve, logs), stage3.tgz, eval JSONs (+ pairs .jsonl.gz).
set -uo pipefail
CALL=${1:?usage: device_full.sh train|eval|val|valeval|bench|smooth}
C=/tmp/full
END_S=${END_S:-570}
LOG=full.log
. scripts/device_preamble.sh
SCALE=${CAMERA_SCALE:-0.5}
CLOUDS=train_clouds_r$($PY -c "print(round($SCALE * 100))")
INIT1=${INIT1:-weights/where_small_paper}
# the held-out pairs (results/heldout_pairs.jsonl: the 1,814 of results/hanging_success.pairs.jsonl,
# five fields each, so that the tree stays under the device's 64 MiB)
HELDOUT=${HELDOUT_PAIRS:-results/heldout_pairs.jsonl}
# the V CEM searches on (VALUE; default stage3.CEM_VALUE, since the fourteenth session)
V_CEM=${VALUE:-weights/value_s16_hardneg}

derive_test() {  # workers
    timeout -k 5 $(($(left) - 20)) $PY -m experiments.derive_dataset --data "$C/ds" --split test \
        --workers "$1" --pairs-from "$HELDOUT" --no-progress >>"$C/logs/derive_test.log" 2>&1
    log "held-out pairs derived: $(ls "$C/ds/derived/test" | wc -l)"
}
export_where() {  # RUN NAME: stage-1 best + latest (+ Stage 2b) -> $C/export_NAME (base: also $C/export)
    local run=$1 name=$2 ex=$C/export_$2 rel=${1#"$C"/}
    local s2b=$INIT1/stage2b
    # a Stage-1-only INIT1 (e.g. the original preset's) takes the committed Stage 2b
    [ -d "$s2b" ] || s2b=weights/where_small_paper/stage2b
    $PY - >>"$C/logs/export_$name.log" 2>&1 <<EOF
import shutil
from omnihang_jax import train
for which in ("best", "latest"):
    dst = "$ex/" + which
    print(which, train.export_weights("$run", dst, ("1",), which=which))
    shutil.copytree("$s2b", dst + "/stage2b", dirs_exist_ok=True)
EOF
    [ "$name" = base ] && ln -sfn "$ex" "$C/export"
    (cd "$C" && tar -czf "$OUT/where_$name.tgz" "export_$name" logs "$rel/stage1/config.json" \
        "$rel/stage1/metrics.jsonl" "$rel/stage1/val_metrics.jsonl" "$rel/stage1/throughput.json" \
        "$rel/stage1/loss.png" 2>/dev/null)
    # the resumable checkpoint (params + Adam state, ~9 MB) for a bare next machine
    (cd "$C" && tar -czf "$OUT/where_${name}_ckpt.tgz" "$rel/stage1" 2>/dev/null)
    log "exported $name: $(tr '\n' ' ' <"$C/logs/export_$name.log" | tail -c 300)"
}
derived_only() {  # PAIRS_JSONL DERIVED_DIR: the lines whose pair file was derived (pairs
    # without a stable pose are not; eval_stage3 refuses a list with missing files)
    $PY - "$1" "$2" <<'EOF'
import json, os, sys
for line in open(sys.argv[1]):
    if os.path.exists(os.path.join(sys.argv[2], json.loads(line)["file"])):
        print(line, end="")
EOF
}
VALPAIRS=${VAL_PAIRS:-results/validation_pairs.jsonl}
derive_val() {  # WORKERS: the 396 pairs of validation OBJECTS (36 a category), full recipe
    timeout -k 5 $(($(left) - 20)) $PY -m experiments.derive_dataset --data "$C/ds" --split train \
        --workers "${1:-2}" --pairs-from "$VALPAIRS" --no-progress >>"$C/logs/derive_val.log" 2>&1
    log "validation pairs derived: $(ls "$C/ds/derived/train" 2>/dev/null | wc -l)"
}

if [ "$CALL" = train ]; then
    # VIEWS (1): views of every pair, view k >= 1 = the pair's k-th other candidate view
    SPLITS=
    # SKIP_PACK=1: a warm machine's pack (e.g. of a PACK_ONLY=1 call) is reused as it is
    if [ -n "${SKIP_PACK:-}" ] && [ -f "$C/pack/pack.json" ]; then
        log "reusing $C/pack: $(tr -d '\n ' <"$C/logs/pack.log" | cut -c1-200)"
    else
    for v in $(seq 0 $((${VIEWS:-1} - 1))); do
        sfx=$([ "$v" -gt 0 ] && echo "_v$v")
        timeout -k 5 $((${DERIVE_S:-240} * (v + 1) - $(date +%s) + T0)) $PY -m experiments.derive_dataset \
            --data "$C/ds" --split train --workers 16 --clouds-only --camera-scale "$SCALE" \
            --view "$v" --no-progress >>"$C/logs/derive_train.log" 2>&1
        log "derived $(ls "$C/ds/derived/$CLOUDS$sfx" | wc -l) training pairs ($CLOUDS$sfx)"
        SPLITS=$SPLITS${SPLITS:+,}$CLOUDS$sfx
    done
    if [ -z "${S3_ONLY:-}" ]; then
    $PY -m experiments.pack_dataset --data "$C/ds" --split "$SPLITS" --out "$C/pack_new" \
        --threads 16 --no-progress >"$C/logs/pack.log" 2>&1 && rm -rf "$C/pack" && mv "$C/pack_new" "$C/pack"
    log "packed: $(tr -d '\n ' <"$C/logs/pack.log" | cut -c1-200)"
    fi
    fi
    # PACK_ONLY=1: derive and pack, then stop (two views take most of a call)
    [ -n "${PACK_ONLY:-}" ] && { log "done (pack only)"; exit 0; }
    # the Stage-3 part reads DS/derived/train: a dataset folder whose train is the clouds
    mkdir -p "$C/ds3/derived" && ln -sfn "$C/ds/recipe.json" "$C/ds3/recipe.json" &&
        ln -sfn "$C/ds/shards" "$C/ds3/shards" && ln -sfn "$C/ds/derived/$CLOUDS" "$C/ds3/derived/train"
    if [ -n "${S3_ONLY:-}" ]; then
        # S3_ONLY=1: the Stage-3 part alone, on all cores, on every derived training pair (a
        # warm next call with S3_ONLY=1 resumes the same job: more seeding, more rounds);
        # the held-out / validation pairs are derived only with TEST_W > 0
        [ "${TEST_W:-0}" -gt 0 ] && { (derive_test "$TEST_W"; derive_val "$TEST_W") & TEST_PID=$!; }
        CHAIN_DS=$C/ds3 STAGE3_STATE=$C/stage3 CHAIN_WORKERS=${S3_W:-15} \
            INIT_VALUE=${INIT_VALUE:-$V_CEM} XLA_PYTHON_CLIENT_MEM_FRACTION=0.6 \
            EXTRA="--pretrain-steps ${S3_PRETRAIN:-2000} --round-pairs 512 --max-pairs ${S3_PAIRS:-0} ${S3_EXTRA:-}" \
            bash scripts/chain/stage3.sh $(($(left) - 10)) "$OUT/stage3.tgz" \
            >>"$C/logs/stage3_part.log" 2>&1
        log "Stage-3 part: exit $? ($(tail -c 600 "$C/stage3/logs/call_$(ls "$C/stage3/logs" | grep -c '^call_').log" | tr '\n' ' '))"
        [ -n "${TEST_PID:-}" ] && wait "$TEST_PID"
        ls -la "$OUT" | tee -a "$OUT/$LOG"
        log "done"
        exit 0
    fi
    if [ -z "${NO_S3:-}" ]; then
        CHAIN_DS=$C/ds3 STAGE3_STATE=$C/stage3 CHAIN_WORKERS=${S3_W:-11} \
            INIT_VALUE=${INIT_VALUE:-$V_CEM} \
            EXTRA="--pretrain-steps 1000 --round-pairs 512 --max-pairs ${S3_PAIRS:-4000}" \
            bash scripts/chain/stage3.sh $(($(left) - 15)) "$OUT/stage3.tgz" \
            >>"$C/logs/stage3_part.log" 2>&1 &
        S3_PID=$!
    fi
    # TEST_W=0: no held-out / validation derive (evaluated elsewhere)
    if [ "${TEST_W:-3}" -gt 0 ]; then
        (derive_test "${TEST_W:-3}"; derive_val "${TEST_W:-3}") &
        TEST_PID=$!
    fi
    BUDGET=$(($(left) - 45))
    # S1_VARIANTS: Stage-1 runs side by side on the one GPU, same data and budget; name -> flags
    # (6daug / 6dyaw / 6dmean / 6dlo: the 6-D head with issue 14's augmentation, the mean set loss or lr 1e-4;
    # with INIT1 = the committed 6-D weights they fine-tune it, beside the plain 6d control)
    declare -A S1V=([base]="" [aa]="" [6d]="--stage1 rotation=6d" [mean]="--stage1 set_loss_mean=true"
        [6daug]="--stage1 rotation=6d --augment-jitter 0.002 --augment-yaw 0.5"
        [6dyaw]="--stage1 rotation=6d --augment-yaw 3.1416"
        [6dmean]="--stage1 rotation=6d --stage1 set_loss_mean=true"
        [6dlo]="--stage1 rotation=6d --lr-stage1 1e-4"
        [6dorig]="--stage1 rotation=6d --preset original")
    PIDS=
    for name in ${S1_VARIANTS:-base}; do
        dir=$C/where$([ "$name" != base ] && echo "_$name")
        log "Stage 1 ($name) for ${BUDGET} s from $INIT1 into $dir"
        $PY -m experiments.train_where --data "$C/pack" --out "$dir" --preset small --stage 1 \
            --steps "${STEPS1:-30000}" --batch "${BATCH1:-128}" --lr-stage1 "${LR1:-5e-4}" \
            --warmup 300 --time-budget "1=$BUDGET" --eval-every 500 --checkpoint-every 1000 \
            $([ "$INIT1" != none ] && echo --init-from "$INIT1") ${S1V[$name]} ${S1_ARGS:-} \
            --no-progress >>"$C/logs/where_$name.log" 2>&1 &
        PIDS="$PIDS $!"
    done
    for p in $PIDS; do wait "$p"; log "Stage 1 run $p: exit $?"; done
    for name in ${S1_VARIANTS:-base}; do
        log "Stage 1 ($name): $(tail -1 "$C/logs/where_$name.log" | cut -c1-200)"
        export_where "$C/where$([ "$name" != base ] && echo "_$name")" "$name"
    done
    [ -n "${TEST_PID:-}" ] && wait "$TEST_PID"
    [ -n "${S3_PID:-}" ] && { wait "$S3_PID"; log "Stage-3 part: exit $?"; }
    ls -la "$OUT" | tee -a "$OUT/$LOG"
    log "done"
    exit 0
fi

if [ "$CALL" = bench ]; then
    # issue 12's latency: the answer pipeline and the paper's, side by side (bench_stage3)
    # BENCH_ARGS: more bench_stage3 flags, e.g. "--batches 1,256 --answers chosen,single"
    # BENCH_BASE=DIR: first the same bench (BENCH_BASE_ARGS) with an earlier commit's package,
    # side by side on this machine, e.g. before the call:
    #   mkdir -p _bench_base && git archive HEAD omnihang_jax experiments | tar -x -C _bench_base
    if [ -n "${BENCH_BASE:-}" ]; then
        for d in weights sim datasets results; do ln -sfn "$PWD/$d" "$BENCH_BASE/$d"; done
        (cd "$BENCH_BASE" && PYTHONPATH=/tmp/site:$PWD timeout $(($(left) - 5)) $PY -m experiments.bench_stage3 \
            --out "$OUT/bench_stage3_base.json" ${BENCH_BASE_ARGS:-${BENCH_ARGS:-}} 2>&1 | tail -8 |
            sed 's/^/[base] /' | tee -a "$OUT/$LOG")
    fi
    timeout $(($(left) - 5)) $PY -m experiments.bench_stage3 --batches 1,16,256 \
        --out "$OUT/bench_stage3.json" ${BENCH_ARGS:-} 2>&1 | tail -8 | tee -a "$OUT/$LOG"
    log "done"
    exit 0
fi

if [ "$CALL" = smooth ]; then
    # issue 12: the answer picked by V averaged around each refined candidate
    # (experiments.smooth_stage3), chosen on the validation-object records of the committed
    # weights, applied to the held-out records of results/hanging_success.json's run
    [ "$(ls "$C/ds/derived/test" 2>/dev/null | wc -l)" -ge 1794 ] || derive_test 16
    [ "$(ls "$C/ds/derived/train" 2>/dev/null | wc -l)" -ge 300 ] || derive_val 16
    timeout $(($(left) - 5)) $PY -m experiments.smooth_stage3 --data "$C/ds" \
        --select-on "${SMOOTH_VAL:-results/validation_where_s11/val_committed.pairs.jsonl.gz}" \
        --apply-to "${SMOOTH_HELD:-results/hanging_success_stage3_s10_answer.pairs.jsonl.gz}" \
        --value weights/value_small_paper --batch 32 --out "$OUT/smooth_stage3.json" ${SMOOTH_ARGS:-} --no-progress 2>&1 |
        tail -4 | tee -a "$OUT/$LOG"
    log "done"
    exit 0
fi

if [ "$CALL" = val ]; then
    # the validation-object pairs (derive if absent) through eval_stage3 with the committed
    # weights: records with every candidate's V and observed-cloud inside counts, for
    # experiments.rerank_stage3 (the answer rule chosen on validation objects). The derive
    # runs every time (it skips pair files already there), so a warm machine's second
    # VAL_PAIRS list (e.g. issue 12's ranker pairs, results/ranker_pairs_b.jsonl) is derived.
    derive_val 16
    derived_only "$VALPAIRS" "$C/ds/derived/train" >"$C/val.jsonl"
    log "validation pairs to evaluate: $(wc -l <"$C/val.jsonl")"
    # VAL_WS="NAME=WEIGHTS ...": several Stage-1/2 weights in turn (e.g. the train call's
    # variants: "6d=/tmp/full/export_6d/best"); default: WHERE_W as VAL_NAME
    for spec in ${VAL_WS:-${VAL_NAME:-where}=${WHERE_W:-weights/where_small_paper}}; do
        name=${spec%%=*} w=${spec#*=}
        [ "$(left)" -gt 60 ] || { log "no time left for $name"; break; }
        log "validation objects: $name ($w)"
        timeout $(($(left) - 5)) $PY -m experiments.eval_stage3 --data "$C/ds" --split train \
            --weights "$w" --value "$V_CEM" \
            --pairs-from "$C/val.jsonl" --workers 15 --batch 16 --out "$OUT/val_$name.json" \
            --label "validation objects, $name ($w)" ${VAL_ARGS:-} --no-progress 2>&1 |
            tail -12 | tee -a "$OUT/$LOG"
    done
    gzip -f "$OUT"/*.pairs.jsonl 2>/dev/null
    # a copy stays on the machine for a warm next call (e.g. train_ranker on the records)
    mkdir -p "$C/records" && cp "$OUT"/*.pairs.jsonl.gz "$C/records/" 2>/dev/null
    log "done"
    exit 0
fi

if [ "$CALL" = valeval ]; then
    # issue 12: the ranking networks chosen on the validation objects, then the held-out run
    # with them, in one call (the rule fixed before looking): the 396 validation-object pairs
    # through eval_stage3 (VAL_ARGS, e.g. "--proposals 10") with every candidate network of
    # RANK_CANDIDATES (default stage3.RANK_VALUES + a warm train call's V,
    # /tmp/full/stage3/run/value) recorded; CEM searches on VALUE (default stage3.CEM_VALUE); experiments.ensemble_stage3 --from-records picks the
    # set (none, or any subset; ties: the smaller) with the best validation mean; then the
    # eval below with that set (EVAL_ARGS gets its --rank-value flags).
    [ "$(ls "$C/ds/derived/train" 2>/dev/null | wc -l)" -ge 300 ] || derive_val 4 &
    [ "$(ls "$C/ds/derived/test" 2>/dev/null | wc -l)" -ge 1794 ] || derive_test 12 &
    wait
    RANKS=${RANK_CANDIDATES:-$([ -d weights/value_s12_hardneg ] && echo weights/value_s12_hardneg) weights/value_s13_hardneg weights/value_s15_hardneg $([ -d "$C/stage3/run/value" ] && echo "$C/stage3/run/value")}
    derived_only "$VALPAIRS" "$C/ds/derived/train" >"$C/val.jsonl"
    log "validation pairs: $(wc -l <"$C/val.jsonl"); ranking candidates: $RANKS"
    timeout $(($(left) - 240)) $PY -m experiments.eval_stage3 --data "$C/ds" --split train \
        --weights "${WHERE_W:-weights/where_small_paper}" --value "$V_CEM" \
        --pairs-from "$C/val.jsonl" --workers 15 --batch 16 --out "$OUT/val_choose.json" \
        --label "validation objects, ranking candidates $RANKS ${VAL_ARGS:-}" \
        $(for r in $RANKS; do echo --rank-value "$r"; done) --rank-with-value ${VAL_ARGS:-} --no-progress 2>&1 |
        tail -6 | tee -a "$OUT/$LOG"
    $PY -m experiments.ensemble_stage3 --from-records --select-on "$OUT/val_choose.pairs.jsonl" \
        --value "$V_CEM" $(for r in $RANKS; do echo --extra-value "$r"; done) \
        --out "$OUT/ensemble_choice.json" --no-progress 2>&1 | tail -2 | tee -a "$OUT/$LOG"
    CHOSEN=$($PY -c "import json; print(' '.join(json.load(open('$OUT/ensemble_choice.json'))['chosen_rank_values']) or 'none')") ||
        { log "error: no ranking chosen (see above)"; exit 3; }
    log "chosen ranking networks: $CHOSEN"
    # HELD_IF_ABOVE=X: a variant's held-out run only when its validation figure (the chosen
    # ranking's mean) beats X, the current pipeline's on the same pairs
    if [ -n "${HELD_IF_ABOVE:-}" ]; then
        BEST=$($PY -c "import json; print(max(r['mean'] for r in json.load(open('$OUT/ensemble_choice.json'))['pipeline_table']))")
        if ! $PY -c "import sys; sys.exit(0 if $BEST > $HELD_IF_ABOVE else 1)"; then
            log "validation $BEST <= $HELD_IF_ABOVE: not better, no held-out run"
            gzip -f "$OUT"/*.pairs.jsonl 2>/dev/null
            exit 0
        fi
        log "validation $BEST > $HELD_IF_ABOVE: the held-out run"
    fi
    # (ensemble_stage3 chose the set by the mean log V with CEM's V: evaluated the same way)
    EVAL_ARGS="${EVAL_ARGS:-} $(for r in $CHOSEN; do echo --rank-value "$r"; done) --rank-with-value"
    NO_NEWV=1
fi

# ---- eval
[ "$(ls "$C/ds/derived/test" 2>/dev/null | wc -l)" -ge 1794 ] || derive_test 16
# the 1,814 pairs of the earlier runs minus the 20 without a stable pose under labels v3
# (not derived): 1,794
derived_only "$HELDOUT" "$C/ds/derived/test" >"$C/heldout.jsonl"
HELDOUT=$C/heldout.jsonl
log "held-out pairs to evaluate: $(wc -l <"$HELDOUT")"
W=${WHERE_W:-$C/export/best}
# (a Stage-1 mix "A+B": its first folder is checked)
[ -d "${W%%+*}" ] || W=weights/where_small_paper  # no train call on this machine: the committed weights
NEWV=$C/stage3/run/value
evaluate() {  # value label out [eval_stage3 flags]
    local value=$1 label=$2 out=$3
    shift 3
    timeout $(($(left) - 10)) $PY -m experiments.eval_stage3 --data "$C/ds" --weights "$W" \
        --value "$value" --pairs-from "$HELDOUT" --workers 15 --batch 16 --out "$OUT/$out.json" \
        --label "$label" "$@" --no-progress 2>&1 | tail -12 | tee -a "$OUT/$LOG"
}
log "eval: Stages 1-2 $W"
TAG=${EVAL_TAG:-heldout}
evaluate "$V_CEM" "${EVAL_LABEL:-Stages 1-2 $W, V ${VALUE:-committed}} ${EVAL_ARGS:-}" \
    "${TAG}_where" ${EVAL_ARGS:-}
# the Stage-3 answer rule chosen on the validation objects, applied once to these records
# (device_slim.sh keeps results/validation_where_s9/val_s9_counts.pairs.jsonl.gz in the tree)
$PY -m experiments.rerank_stage3 --select-on results/validation_where_s9/val_s9_counts.pairs.jsonl.gz \
    --apply-to "$OUT/${TAG}_where.pairs.jsonl" --out "$OUT/${TAG}_rerank.json" 2>&1 | tail -2 | tee -a "$OUT/$LOG"
if [ -z "${NO_NEWV:-}" ] && [ -d "$NEWV" ] && [ "$(left)" -gt 200 ]; then
    evaluate "$NEWV" "Stages 1-2 $W, the train call's hard-negative V" "${TAG}_both" ${EVAL_ARGS:-}
fi
gzip -f "$OUT"/*.pairs.jsonl 2>/dev/null
log "done"
