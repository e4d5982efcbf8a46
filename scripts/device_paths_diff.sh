# Issue 13 (forty-first session; forty-second: any seed, reference and rule), a device call: the
# cheap paired protocol on the device's CPU cores. Per seed: the route rule's decisions against a
# reference run (scripts/approach_decisions.py diff, on this machine's CPU), then the pairs whose
# first plan it changes planned by scripts/device_paths.sh (a variant per seed, one after another).
#
#   bash scripts/device_paths_diff.sh first 0.3          # the forty-first session's seed-4 call
#   SEEDS="3 4" REF_3=results/paths_s41/first_seed3.pairs.jsonl REF_4=... GAP=0.01 TRIES=10 \
#       TAG=low bash scripts/device_paths_diff.sh first 0.15
#
# MODE (fill/first) and T (the route threshold) as arguments; SEEDS (default 4), REF_<seed> (the
# reference run of each seed; seed 4's default is the s37 rule's 49-pair device run), GAP (end
# gap, m), TRIES, TAG (names the lists and variants) from the environment; PLANNED=1 skips the
# diff and plans the lists already in LISTS (default out/s42/dev/lists, carried).
set -uo pipefail
MODE=$1 T=$2
SEEDS=${SEEDS:-4} GAP=${GAP:-0.01} TRIES=${TRIES:-10} TAG=${TAG:-$MODE}
REF_4=${REF_4:-results/paths_s38/s37_device_seed4_49pairs.pairs.jsonl}
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site .whl_min/*.whl .whl_train/*.whl .whl_plan/*.whl 2>/dev/null
export PYTHONPATH=/tmp/site:$PWD JAX_PLATFORMS=cpu PYTHONUNBUFFERED=1
L=${LISTS:-out/s42/dev/lists}
C0=--clear-path,0.03,--clear-keep-ball,0.045,--fallback-far-threshold,0.56,--fallback-time,30,--retreat,0.045,--approach-open-side,--approach-replan,plain,--approach,weights/approach_s37_8k,--approach-threshold,0.8,--routes,weights/approach_routes_s40_8k,--routes-check,checker
mkdir -p $L
RULE="--routes-threshold $T --routes-mode $MODE --routes-check checker --routes-end-gap $GAP --routes-tries $TRIES"
if [ -z "${PLANNED:-}" ]; then  # the seeds' diffs side by side, 4 cores each
    k=0
    for s in $SEEDS; do
        ref=REF_$s
        taskset -c $((k * 4))-$((k * 4 + 3)) python3 scripts/approach_decisions.py diff --reference "${!ref}" \
            --approach weights/approach_s37_8k --threshold 0.8 --open-side --routes weights/approach_routes_s40_8k \
            $RULE --out $L/plan_${TAG}_seed$s.txt >$L/diff_seed$s.log 2>&1 &
        k=$(((k + 1) % 4))
    done
    wait
    for s in $SEEDS; do echo "seed $s: $(grep -v "^WARN\|leaked\|nanobind" $L/diff_seed$s.log | tail -1)"; done
fi
V=""
for s in $SEEDS; do
    cp $L/plan_${TAG}_seed$s.* $OUT/ 2>/dev/null
    [ -s $L/plan_${TAG}_seed$s.txt ] || { echo "seed $s: no pair changes"; continue; }
    V="$V ${TAG}$s=$C0,--routes-mode,$MODE,--routes-threshold,$T,--routes-end-gap,$GAP,--routes-tries,$TRIES,--planner-seed,$s,--only-pairs,$L/plan_${TAG}_seed$s.txt"
done
[ -n "$V" ] || exit 0
END_S=${END_S:-540} VARIANTS="$V" bash scripts/device_paths.sh
