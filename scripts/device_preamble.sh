# Sourced by the device job scripts (scripts/device_evaluate.sh, scripts/device_nce.sh,
# scripts/device_paths.sh, scripts/device_ranker.sh), which set first: CALL (the call's name),
# C (the job's state folder on the machine), END_S (seconds the call may use) and LOG (the log
# file's name under $OUT). Gives T0, OUT, PY, log(), left(); installs the carried wheels once
# per machine into /tmp/site (.whl_min + .whl_train, and .whl_plan when carried; SKIP_INSTALL=1:
# a local dry run), records the call in $C/calls, copies the dataset's recipe + shards to
# $C/ds once.
T0=$(date +%s)
OUT=${OUT:-/tmp/out}
mkdir -p "$OUT" "$C/logs"
log() { echo "[$(($(date +%s) - T0)) s] $*" | tee -a "$OUT/$LOG"; }
left() { echo $((END_S - $(date +%s) + T0)); }
PY=${PY:-python3}
if [ -z "${SKIP_INSTALL:-}" ]; then
    wheels=()
    [ -e /tmp/site/mujoco ] || wheels+=(.whl_min/*.whl .whl_train/*.whl)
    if [ ! -e /tmp/site/ompl ] && compgen -G ".whl_plan/*.whl" >/dev/null; then
        wheels+=(.whl_plan/*.whl)
    fi
    if [ "${#wheels[@]}" -gt 0 ]; then
        $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site \
            "${wheels[@]}" 2>&1 | grep -v "already exists" || true
        [ -e /tmp/site/mujoco ] || { log "wheel install failed"; exit 5; }
    fi
fi
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
log "call $CALL; earlier calls on this machine: $(cat "$C/calls" 2>/dev/null | tr '\n' ' ')"
echo "$CALL" >>"$C/calls"
command -v nvidia-smi >/dev/null && nvidia-smi -L | tee -a "$OUT/$LOG"
if [ ! -e "$C/ds/recipe.json" ]; then
    mkdir -p "$C/ds" && cp -r datasets/paper/recipe.json datasets/paper/shards "$C/ds/"
fi
