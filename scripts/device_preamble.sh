# Sourced by the device job scripts (scripts/device_chain.sh, scripts/device_full.sh), which
# set first: CALL (the call's name), C (the job's state folder on the machine), END_S (seconds
# the call may use) and LOG (the log file's name under $OUT). Gives T0, OUT, PY, log(),
# left(); installs the carried wheels once per machine (SKIP_INSTALL=1: a local dry run),
# records the call in $C/calls, copies the dataset's recipe + shards to $C/ds once.
T0=$(date +%s)
OUT=${OUT:-/tmp/out}
mkdir -p "$OUT" "$C/logs"
log() { echo "[$(($(date +%s) - T0)) s] $*" | tee -a "$OUT/$LOG"; }
left() { echo $((END_S - $(date +%s) + T0)); }
PY=${PY:-python3}
if [ -z "${SKIP_INSTALL:-}" ] && [ ! -e /tmp/site/mujoco ]; then
    $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site \
        .whl_min/*.whl .whl_train/*.whl || { log "wheel install failed"; exit 5; }
fi
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
log "call $CALL; earlier calls on this machine: $(cat "$C/calls" 2>/dev/null | tr '\n' ' ')"
echo "$CALL" >>"$C/calls"
command -v nvidia-smi >/dev/null && nvidia-smi -L | tee -a "$OUT/$LOG"
if [ ! -e "$C/ds/recipe.json" ]; then
    mkdir -p "$C/ds" && cp -r datasets/paper/recipe.json datasets/paper/shards "$C/ds/"
fi
