# Issue 13 (forty-first session), a device call: the cheap paired protocol on OMPL seed 4 (the s37 rule's
# 49-pair device run as reference): the checked route rule's decisions (diff, on this machine's
# CPU), then the changed pairs planned by scripts/device_paths.sh
set -uo pipefail
MODE=$1 T=$2
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site .whl_min/*.whl .whl_train/*.whl .whl_plan/*.whl 2>/dev/null
export PYTHONPATH=/tmp/site:$PWD JAX_PLATFORMS=cpu PYTHONUNBUFFERED=1
mkdir -p out/s41/dev/lists
python3 scripts/approach_decisions.py diff --reference results/paths_s38/s37_device_seed4_49pairs.pairs.jsonl \
  --approach weights/approach_s37_8k --threshold 0.8 --open-side --routes weights/approach_routes_s40_8k \
  --routes-threshold $T --routes-mode $MODE --routes-check checker --routes-end-gap 0.01 \
  --out out/s41/dev/lists/plan_${MODE}_seed4.txt 2>&1 | grep -v "^WARN\|leaked\|nanobind" | tail -2
cp out/s41/dev/lists/plan_${MODE}_seed4.* $OUT/
C=--clear-path,0.03,--clear-keep-ball,0.045,--fallback-far-threshold,0.56,--fallback-time,30,--retreat,0.045,--approach-open-side,--approach-replan,plain,--approach,weights/approach_s37_8k,--approach-threshold,0.8,--routes,weights/approach_routes_s40_8k,--routes-check,checker,--routes-end-gap,0.01
END_S=${END_S:-540} VARIANTS="${MODE}4=$C,--routes-mode,$MODE,--routes-threshold,$T,--planner-seed,4,--only-pairs,out/s41/dev/lists/plan_${MODE}_seed4.txt" bash scripts/device_paths.sh
