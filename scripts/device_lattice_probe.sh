#!/usr/bin/env bash
# Issue 13 (forty-third session), a device call: scripts/probe_checked_lattice.py over the 80
# held-out goals in N shards at once (default 8, sharing the GPU: the hybrid checker's networks
# run there), the shards' outputs and logs tarred into $OUT/lattice.tgz, the summary beside it
# ($OUT/checked_lattice.json). END_S bounds each shard (a shard killed keeps the goals it wrote).
#   bash scripts/device_lattice_probe.sh [extra probe args]
set -uo pipefail
N=${N:-8} END_S=${END_S:-540}
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site .whl_min/*.whl .whl_train/*.whl .whl_plan/*.whl 2>/dev/null
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false XLA_PYTHON_CLIENT_MEM_FRACTION=0.1
mkdir -p /tmp/lat
for i in $(seq 0 $((N - 1))); do
    timeout -s INT $END_S python3 scripts/probe_checked_lattice.py --shard $i/$N --no-progress \
        --out /tmp/lat/lattice_$i.json "$@" >/tmp/lat/lattice_$i.log 2>&1 &
done
wait
tail -2 /tmp/lat/lattice_0.log
python3 scripts/probe_checked_lattice.py --summarise /tmp/lat/lattice_*.json --out $OUT/checked_lattice.json | tail -60
tar czf $OUT/lattice.tgz -C /tmp lat
