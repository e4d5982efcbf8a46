#!/usr/bin/env bash
# Issue 12 (twenty-sixth session): the ranking networks on T evenly spaced subsets of the
# clouds (stage3.subset_clouds), scored on the recorded candidates of the committed pipeline's
# validation-object and held-out runs (experiments.rank_subsets; no simulation).
#
#   python -m experiments.train_ranker slim results/validation_where_s26/val_base_s24.pairs.jsonl.gz out/s26/val_base.npz
#   python -m experiments.train_ranker slim results/hanging_success_stage3_s22_rankset.pairs.jsonl.gz out/s26/held_s22.npz
#   MORE=1 bash scripts/device_slim.sh out
#   run(carry=[".whl_min", ".whl_train", "out/s26"], command="bash scripts/device_subsets.sh")
#   bash scripts/device_slim.sh in
#
# Derives both tables' pairs (full recipe, the runs' own renders) on 16 workers, then scores.
# SUBSETS (1,2,4,8): the T compared; SUBSETS_BATCH (16 pairs x 32 candidates: at 64 the near-point
# network's XLA compile did not finish in 450 s on an H200). Back in $OUT: rank_subsets.json, rank_subsets_scores.npz,
# subsets.log. A warm machine's $C/ds/derived/test then serves `device_full.sh eval`.
set -uo pipefail
CALL=subsets
C=/tmp/full
END_S=${END_S:-580}
LOG=subsets.log
. scripts/device_preamble.sh
SEL=${SUBSETS_SELECT:-out/s26/val_base.npz}
APP=${SUBSETS_APPLY:-out/s26/held_s22.npz}
# the pairs jsonl of a slim table: device_ranker.sh's pairs_of, sourced without running it
eval "$(sed -n '/^pairs_of() {/,/^}/p' scripts/device_ranker.sh)"
pairs_of "$SEL" >"$C/sel_pairs.jsonl"
pairs_of "$APP" >"$C/app_pairs.jsonl"
for s in train:sel test:app; do
    timeout -k 5 $(($(left) - 120)) $PY -m experiments.derive_dataset --data "$C/ds" --split "${s%%:*}" \
        --workers 16 --pairs-from "$C/${s##*:}_pairs.jsonl" --no-progress >>"$C/logs/derive_subsets.log" 2>&1
    log "derived ${s%%:*}: $(ls "$C/ds/derived/${s%%:*}" | wc -l) pair files"
done
timeout -k 5 $(($(left) - 10)) $PY -m experiments.rank_subsets --select-on "$SEL" --apply-to "$APP" \
    --data "$C/ds" --subsets "${SUBSETS:-1,2,4,8}" --batch "${SUBSETS_BATCH:-16}" --scores "$OUT/rank_subsets_scores.npz" \
    --out "$OUT/rank_subsets.json" --no-progress 2>&1 | grep -v Warning | tee -a "$OUT/$LOG"
log "done"
