#!/usr/bin/env bash
# Set up and run the main job:  scripts/main.sh [OUT] [--assets]
#  1. OUT/hang: hang the built-in object on the built-in hook (held-out mug_0016 on held-out
#     single_rod_hook_0001, neither seen in training): partial clouds rendered from one view,
#     the default where-to-hang answer (omnihang_jax.where.DEFAULT: Stages 1-3, the rankers,
#     the answer rule), every candidate simulated in MuJoCo, a path planned by the default
#     planner (omnihang_jax.paths.DEFAULT), reference poses from the data engine's sampler
#     (--search); writes result.json, scene.xml (MuJoCo's viewer), hang.png and viewer.html;
#  2. OUT/hang_heldout: PAIRS (default 3) held-out library pairs spread over the support
#     families and object categories; for each, the answer from the clouds alone (checked on the
#     observed clouds) is simulated on the true meshes, and the rate is quoted beside the one
#     `python -m experiments.evaluate where` measured (results/hanging_success.json);
#  --assets: also the asset library + physics showcase (OUT/assets).
# A few minutes on 2 CPU cores after setup, most of it compiling the networks once.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=out
ASSETS=0
for arg in "$@"; do
  case "$arg" in
    --assets) ASSETS=1 ;;
    -h|--help) sed -n '2,15p' "$0"; exit 0 ;;
    -*) echo "error: unknown option $arg (scripts/main.sh [OUT] [--assets])" >&2; exit 2 ;;
    *) OUT="$arg" ;;
  esac
done
PAIRS=${PAIRS:-3}
bash scripts/setup.sh
if [ "$ASSETS" = 1 ]; then
  .venv/bin/python -m experiments.assets --out "$OUT/assets"
fi
.venv/bin/python -m experiments.hang --out "$OUT/hang" --search || [ $? = 3 ]  # 3: no candidate hangs (still drawn)
# held-out pairs: the default answer from the clouds, judged on the meshes (no planner)
.venv/bin/python -m experiments.hang --heldout "$PAIRS" --out "$OUT/hang_heldout" --no-plan
echo "main job done: $OUT/hang (hang.png, viewer.html, scene.xml, result.json), $OUT/hang_heldout"
echo "open the page: $OUT/hang/viewer.html; the scene: .venv/bin/python -m mujoco.viewer --mjcf=$OUT/hang/scene.xml"
[ "$ASSETS" = 1 ] && echo "asset showcase: $OUT/assets" || true
