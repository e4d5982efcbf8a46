#!/usr/bin/env bash
# The paths figure on the device machine's CPU cores: `python -m experiments.evaluate paths`
# for each planner config in CONFIGS (default: "default paper_nce"), WORKERS processes each
# (JAX on the CPU), PAIRS held-out pairs (default 300), one after another.
#
#   mkdir -p .whl_plan && pip download --no-deps --only-binary=:all: --python-version 3.12 \
#       --implementation cp --platform manylinux_2_17_x86_64 -d .whl_plan ompl==2.0.1
#   run(carry=[".whl_min", ".whl_train", ".whl_plan"], timeout_s=600,
#       command="bash scripts/device_paths.sh")
#
# A warm next call resumes a config cut short (its records stay in /tmp/paths/). Back in $OUT:
# paths.log, paths.json (every config's entry) and paths_CONFIG.jsonl (its per-pair records).
set -uo pipefail
CALL=paths
C=/tmp/paths
END_S=${END_S:-580}
LOG=paths.log
. scripts/device_preamble.sh
if [ ! -e /tmp/site/ompl ]; then
    $PY -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl_plan/*.whl ||
        { log "ompl install failed"; exit 5; }
fi
log "$(nproc) cores; configs ${CONFIGS:=default paper_nce}"
for config in $CONFIGS; do
    [ "$(left)" -gt 60 ] || { log "no time left for $config"; break; }
    timeout -k 5 $(($(left) - 10)) $PY -m experiments.evaluate paths --config "$config" \
        --workers "${WORKERS:-16}" --pairs "${PAIRS:-300}" --records "$C/paths_$config.jsonl" \
        --results "$OUT/paths.json" --no-progress >"$C/logs/$config.log" 2>&1
    log "$config: exit $? | $(grep -E '"(precision|recall|f1)"' "$C/logs/$config.log" | tr -d ' \n')"
    cp "$C/paths_$config.jsonl" "$OUT/" 2>/dev/null
done
log "done"
