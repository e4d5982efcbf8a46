#!/usr/bin/env bash
# The device carries the working tree + carry in at most 64 MiB; the tree alone is ~57 MiB
# and the wheels (.whl_min + .whl_train) ~12 MiB. Before a device call, move the committed
# files no device job reads (older runs' records, CPU weights, variant pair files) aside;
# after it, put them back (git shows them unchanged). Never commit while they are aside.
#
#   bash scripts/device_slim.sh out     # before run(...); MORE=1, plus PATHS=1 for a planner
#                                       # call or STAGE3=1 for a Stage-3 val / eval / bench call
#   bash scripts/device_slim.sh in      # after
set -euo pipefail
ASIDE=${ASIDE:-/tmp/device_aside}
LIST=(
    results/model_940pairs results/previous_model results/labels_v1 results/train_where_paper
    results/hanging_success_select_penetration.pairs.jsonl results/hanging_success_demo.pairs.jsonl
    results/hanging_success_stage3_k10.pairs.jsonl.gz results/hanging_success_stage3_separated.pairs.jsonl.gz
    results/hanging_success_stage3_cem2rounds.pairs.jsonl.gz results/hanging_success_stage3.pairs.jsonl.gz
    weights/collision_fast_cpu weights/collision_fast_cpu_far weights/collision_fast_cpu_stable
    results/hanging_success_stage3_s8.pairs.jsonl.gz results/hanging_success_stage2_clearance_8mm.pairs.jsonl.gz
    results/paths_hybrid.pairs.jsonl results/train_where_session8 results/stage3_train_s8
    results/train_where_session9 results/stage3_train_s9 results/heldout_cpu_s9
    results/validation_where_s9/val_6d.pairs.jsonl.gz
    # (kept in the tree: the records device_full.sh's eval and smooth calls read)
    results/hanging_success_stage3_s9.pairs.jsonl.gz results/hanging_success_stage2_clearance_s9_0.pairs.jsonl.gz
    results/hanging_success_stage2_clearance_s9_12mm.pairs.jsonl.gz results/hanging_success_stage2_clearance_s9_8mm.pairs.jsonl.gz
    results/validation_where_s10/val_6dlatest.pairs.jsonl.gz results/validation_where_s11/val_s11_6d.pairs.jsonl.gz
    results/hanging_success_stage3_s11_k10.pairs.jsonl.gz results/hanging_success_stage3_s11_6dft2.pairs.jsonl.gz
    results/hanging_success_stage3_s11_views2.pairs.jsonl.gz results/validation_where_s11/val_v2.pairs.jsonl.gz
    results/train_where_session10 results/train_where_session11 results/device
    # (twelfth session: the wheels are 12.3 MiB; the collision weights, K=10 records and figures
    # are read by no device_full.sh call)
    weights/collision_fast_gpu weights/collision_fast_gpu_near weights/collision_fast_gpu_near_crop
    results/validation_where_s11/val_k10.pairs.jsonl.gz docs/img
    # (thirteenth session: the answer records of the tenth and twelfth sessions' runs, read by none)
    results/hanging_success_stage3_s10_answer.pairs.jsonl.gz results/hanging_success_stage3_s12_ens.pairs.jsonl.gz
    results/validation_where_s12 results/stage3_train_s12
    results/hanging_success_stage3_s13_k10ens.pairs.jsonl.gz results/validation_where_s13 results/stage3_train_s13
    # (fourteenth session: device_full.sh reads the held-out pairs from results/heldout_pairs.jsonl;
    # the older device_stage3.sh / device_chain.sh still read hanging_success.pairs.jsonl: put it
    # back with `in` before using them)
    results/hanging_success.pairs.jsonl results/hanging_success_stage3_s14_cemv.pairs.jsonl.gz
    results/validation_where_s14 results/stage3_train_s14 results/stage3_train_s15
    # (the ranking networks' first set, s12, is no default any more: carry it by hand to compare)
    weights/value_s12_hardneg
    # (fifteenth session: CEM searches on value_s16_hardneg; the earlier CEM Vs, this session's
    # records and older large pair files are read by no device call; value_small_paper only by
    # `smooth`: put it back by hand for that call. val_s9_counts.pairs stays: the `eval` call's
    # rerank step reads it)
    weights/value_s14_hardneg weights/value_small_paper results/validation_where_s11/val_committed.pairs.jsonl.gz
    results/hanging_success_stage2_clearance_s14_12mm.pairs.jsonl.gz
    results/hanging_success_stage3_s15_default.pairs.jsonl.gz results/hanging_success_stage3_s16_cemv.pairs.jsonl.gz
    results/validation_where_s15 results/stage3_train_s16 results/release_lift
    results/hanging_success_stage1_select_lift_s15.pairs.jsonl.gz results/hanging_success_stage12_select_clear8_s15.pairs.jsonl.gz
    results/hanging_success_stage3_s16_k16.pairs.jsonl.gz
    # (sixteenth session: the new collision weights, Stage-2 training records; the Stage-2
    # candidate weights/where_s16_stage2ft stays for the val call that compares it)
    weights/collision_s16_planner weights/collision_s16_control results/train_where_s16_stage2
    # (seventeenth session: the ranking Vs s13 / s15 are no default since the fifteenth; the
    # original-preset Stage 1 (19 MB) is read only by calls that evaluate the Stage-1 / 1+2
    # answers or a Stage-1 mix: put it back by hand for those and move tests/ docs/ aside instead
    # (docs/device_runs.md, seventeenth session); this session's records)
    weights/value_s13_hardneg weights/value_s15_hardneg weights/where_original_paper
    results/train_where_s17 results/validation_where_s17 results/hanging_success_stage12_orig_s17.pairs.jsonl.gz
    results/hanging_success_stage12_orig_clear4_s17.pairs.jsonl.gz results/hanging_success_stage1_network_orig_s17.pairs.jsonl.gz
    results/hanging_success_stage3_s17_orig.pairs.jsonl.gz
    # (nineteenth session: the held-out records of keys 1 and 2, 19 MB; carry them by hand to
    # a call that reranks them)
    results/hanging_success_stage3_s19_seed1.pairs.jsonl.gz results/hanging_success_stage3_s19_seed2.pairs.jsonl.gz
    # (twentieth session: room for the ranker's carried tables, out/ranker_s20/; the collision
    # weights and the planner's selection file are read by no device_full.sh / device_ranker.sh
    # call: put them back by hand for an NCE call)
    weights/collision_s18_contact weights/collision_s18_small results/validation_where_s16
    results/paths_hybrid_s18_joint95_selection.json results/hanging_success_stage12_lift5_s16.pairs.jsonl.gz
    tests/fixtures
    # (twenty-first session: the twentieth session's held-out records with the ranker, 21 MB,
    # read by no device call; their slim tables travel in out/ranker_s20/held)
    results/hanging_success_stage3_s20_ranker.pairs.jsonl.gz
    results/hanging_success_stage3_s20_ranker_seed1.pairs.jsonl.gz
    # (twenty-second session: the three rankers' held-out records, 13 MB, read by no device call)
    results/hanging_success_stage3_s22_rankset.pairs.jsonl.gz
    # (thirtieth session: the default's held-out records under keys 1 and 2, 34 MB, read by no
    # device call)
    results/hanging_success_stage3_s30_k10_view0_seed1.pairs.jsonl.gz
    results/hanging_success_stage3_s30_k10_view1of2_seed1.pairs.jsonl.gz
    results/hanging_success_stage3_s30_k10_view0_seed2.pairs.jsonl.gz
    results/hanging_success_stage3_s30_k10_view1of2_seed2.pairs.jsonl.gz
)
# MORE=1 (twenty-second session): with three rankers (13.5 MB) the eval call's tree is ~59 MiB;
# these are read by no device_full.sh eval / bench call either (the ranker's scores and pair
# lists, the planner's records, tests and docs)
# (forty-eighth session: the second object completion, 6.9 MB, read by no device call but a
# COMPLETION=1 one)
LIST+=(weights/completion_s48)
if [ -n "${MORE:-}" ]; then
    # (tests/ and docs/ go whole: drop the entries inside them, or `mv tests` would nest)
    KEEP=()
    for p in "${LIST[@]}"; do case $p in tests/* | docs/*) ;; *) KEEP+=("$p") ;; esac; done
    LIST=("${KEEP[@]}")
    LIST+=(results/ranker_s21 results/ranker_s20 results/ranker_pairs_a.jsonl results/ranker_pairs_b.jsonl
        results/ranker_pairs_c.jsonl results/ranker_pairs_d.jsonl results/stage3_train
        results/train_where_session7 results/cross_engine_ablation.json tests docs)
    for f in results/paths*.json results/paths*.jsonl results/*_selection.json results/rerank_stage3_*.json \
        results/cross_engine*.json results/*judges* results/validation_pairs_all.jsonl \
        results/dataset_card.json results/stage3_train_chain; do LIST+=("$f"); done
    # (twenty-seventh session: what the twenty-sixth session moved aside by hand: the completion
    # and transit-NCE weights, the s22 ranker tables, the s26 records; read by no eval / val /
    # bench call)
    LIST+=(weights/completion_s25 weights/collision_s23_transit results/ranker_s22
        results/hanging_success_stage3_s26_view4of8.pairs.jsonl.gz results/rank_subsets_s26)
    # (twenty-seventh session: the two views' held-out and validation records, 23 MB)
    LIST+=(results/hanging_success_stage3_s27_k10_view0.pairs.jsonl.gz
        results/hanging_success_stage3_s27_k10_view1of2.pairs.jsonl.gz)
    for f in results/validation_where_s26/*.pairs.jsonl.gz results/validation_where_s27/*.pairs.jsonl.gz \
        results/validation_where_s44/*.pairs.jsonl.gz; do
        LIST+=("$f")
    done
    # (thirtieth session: the NCE variants of the twenty-eighth and twenty-ninth sessions, moved
    # by hand until now; read by no eval / val / bench / paths call)
    LIST+=(weights/collision_s28_control weights/collision_s28_completed weights/collision_s29_mined
        weights/collision_s29_mined30)
    # (thirty-first session: the third view's held-out records, 8.5 MB, and the ranker study)
    LIST+=(results/hanging_success_stage3_s31_k10_view3of4.pairs.jsonl.gz results/ranker_s31)
    # (thirty-second session: the third view's held-out records under keys 1 and 2, 17 MB, and
    # the answer-rule studies; read by no device call)
    LIST+=(results/hanging_success_stage3_s32_k10_view3of4_seed1.pairs.jsonl.gz
        results/hanging_success_stage3_s32_k10_view3of4_seed2.pairs.jsonl.gz
        results/union_rules_s32_views2.json results/union_rules_s32_views3.json)
fi
# (forty-fourth session) what the thirty-eighth to forty-third sessions moved aside by hand before
# every device_paths.sh call, 7 MiB: the earlier planner probes' records and approach networks,
# read by no eval / val / bench / device_paths.sh call. Put back by hand what a call reads: a
# seed-4 scripts/device_paths_diff.sh reads REF_4 in results/paths_s38, the lattice probe
# (scripts/device_lattice_probe.sh) results/paths_s39/dogleg_heldout.json
HAND=(results/paths_s38 results/paths_s39 results/paths_s40 weights/approach_s35
    weights/approach_s35_6k weights/approach_routes_s40
    results/paths_s41/route_check_validation.json results/paths_s42/route_check_validation_low.json)
# STAGE3=1 (forty-fourth session; device_full.sh val / eval / bench, with MORE=1): the planner's
# records and approach networks go too (PATHS=1 would move the pipeline's weights aside). With
# MORE=1 alone the tree was 56.7 MiB in disk blocks, over the 64 MiB with the wheels (12.2 MiB);
# with STAGE3=1 51.7 (63.9 with the wheels: little room left). Of results/validation_where_s9
# only val_s9_counts.pairs.jsonl.gz stays: the eval call's rerank step reads it
if [ -n "${STAGE3:-}" ]; then
    LIST+=("${HAND[@]}" results/paths_s41 results/paths_s42 results/paths_s43 results/paths_scenes
        weights/approach_s37_8k weights/approach_routes_s40_8k results/probe_symmetry_s41_key0.json
        results/ranker_pairs_e.jsonl)
    for f in results/validation_where_s9/*; do
        [ "$f" = results/validation_where_s9/val_s9_counts.pairs.jsonl.gz ] || LIST+=("$f")
    done
fi
# PATHS=1 (twenty-fourth session; device_paths.sh): as NCE=1, and the best hybrid's selection
# file stays too
if [ -n "${PATHS:-}" ]; then
    NCE=1
    # (forty-fourth session) the hand-moved items, and the Stage-3 validation records no planner reads
    LIST+=("${HAND[@]}" results/validation_where_s9)
    KEEP=()
    for p in "${LIST[@]}"; do [ "$p" = results/paths_hybrid_s18_joint95_selection.json ] || KEEP+=("$p"); done
    LIST=("${KEEP[@]}")
fi
# NCE=1 (twenty-third session; device_nce.sh calls seeded from the contact NCE): the contact
# NCE's weights stay, the pipeline's weights go aside (no NCE call reads them)
if [ -n "${NCE:-}" ]; then
    KEEP=()
    for p in "${LIST[@]}"; do [ "$p" = weights/collision_s18_contact ] || KEEP+=("$p"); done
    LIST=("${KEEP[@]}")
    LIST+=(weights/where_small_paper weights/value_s20_ranker weights/value_s21_big1 weights/value_s21_near
        weights/value_s16_hardneg)
fi
# COMPLETION=1 (twenty-eighth session; device_nce.sh training the completion-aware NCE): the
# shape-completion networks stay
if [ -n "${COMPLETION:-}" ]; then
    KEEP=()
    for p in "${LIST[@]}"; do [ "$p" = weights/completion_s25 ] || [ "$p" = weights/completion_s48 ] || KEEP+=("$p"); done
    LIST=("${KEEP[@]}")
fi
# RANKER=1 (device_ranker.sh calls): the pipeline's weights but CEM's V (the ranker's init)
[ -n "${RANKER:-}" ] && LIST+=(weights/where_small_paper weights/value_s20_ranker weights/value_s21_big1 weights/value_s21_near)
# POOLS=1 (forty-seventh session; scripts/device_pools.sh): every results/ entry but the pair lists
# a records / train / score call reads (the held-out and validation lists, ranker_pairs_*.jsonl);
# POOLS_WEIGHTS="where_small_paper value_s16_hardneg ..." also moves those weights/ folders (a
# train / score call reads only the rankers it starts from; the records call needs them all)
if [ -n "${POOLS:-}" ]; then
    for f in results/*; do
        case $f in results/heldout_pairs.jsonl | results/validation_pairs.jsonl | results/ranker_pairs_*.jsonl) ;; *) LIST+=("$f") ;; esac
    done
    for w in ${POOLS_WEIGHTS:-}; do LIST+=("weights/$w"); done
fi
case ${1:-} in
out)
    mkdir -p "$ASIDE"
    for p in "${LIST[@]}"; do
        [ -e "$p" ] || continue
        # an entry inside a folder also listed goes with that folder (moving the folder onto
        # the part of it already aside would nest it: forty-fourth session)
        inside=
        for q in "${LIST[@]}"; do case $p in "$q"/*) inside=1 ;; esac; done
        [ -n "$inside" ] && continue
        mkdir -p "$ASIDE/$(dirname "$p")" && mv "$p" "$ASIDE/$p"
    done
    (git ls-files -z; git ls-files -z --others --exclude-standard) | xargs -0 stat -c %s 2>/dev/null |
        awk '{s+=$1} END {printf "tree now %.1f MiB\n", s/1048576}' || true  # (stat fails on the files aside)
    # the device tool counts disk blocks, a little more than the sizes above: this is the figure
    # to keep under 64 MiB minus the carried wheels (~12.2 MiB)
    (git ls-files -z; git ls-files -z --others --exclude-standard) | xargs -0 du -c 2>/dev/null |
        tail -1 | awk '{printf "in disk blocks %.1f MiB\n", $1/1024}' || true
    ;;
in)
    [ -d "$ASIDE" ] || { echo "nothing aside in $ASIDE"; exit 0; }
    (cd "$ASIDE" && find . -type f -o -type l) | while read -r f; do
        mkdir -p "$(dirname "$f")" && mv -n "$ASIDE/$f" "$f"
    done
    rm -rf "$ASIDE"
    git status --short | head
    ;;
*)
    echo "usage: device_slim.sh out|in" >&2
    exit 2
    ;;
esac
