#!/usr/bin/env bash
# Device side of scripts/split_wheels.sh: stash the part this call carried, and once all
# parts are there, join, check and unpack them.
#
#   bash scripts/join_wheels.sh stash K        move .whlparts/pK into the stash (calls 1..N-1)
#   bash scripts/join_wheels.sh join K DEST    stash part K, verify every part, unpack to DEST
#
# The stash is $WHL_STASH (default /root/.omnihang_whlparts), outside the repo copy, so it
# does not depend on how the tool syncs the working tree; it survives between calls only
# while the machine stays warm (30 s idle). Exit 3: parts missing (the machine went back
# between calls: start again from part 1); exit 4: a checksum differs.
set -euo pipefail
STASH=${WHL_STASH:-/root/.omnihang_whlparts}
mode=$1
k=$2
mkdir -p "$STASH"
src=".whlparts/p$k"
if [ -d "$src" ]; then
    cp -f "$src"/bundle.part.* "$STASH"/
    cp -f "$src"/MANIFEST "$STASH"/MANIFEST
else
    echo "no $src in this call's tree (was it named in carry?)" >&2
fi
echo "stash $STASH:"
ls -l "$STASH"
[ "$mode" = stash ] && exit 0
dest=$3
cd "$STASH"
n=$(awk '/^parts/ {print $2}' MANIFEST)
missing=0
for p in $(seq 0 $((n - 1))); do
    [ -f "bundle.part.$p" ] || {
        echo "MISSING part $((p + 1)) of $n" >&2
        missing=1
    }
done
[ $missing = 0 ] || exit 3
grep '  bundle.part' MANIFEST | sha256sum -c --quiet || exit 4
whole=$(cat $(ls bundle.part.* | sort -t. -k3 -n) | sha256sum | cut -d' ' -f1)
[ "$whole" = "$(awk '/^whole/ {print $2}' MANIFEST)" ] || exit 4
mkdir -p "$dest"
if grep -q '^codec tar.xz' MANIFEST; then  # python's lzma: no xz binary needed there
    cat $(ls bundle.part.* | sort -t. -k3 -n) |
        python3 -c "import lzma, shutil, sys; shutil.copyfileobj(lzma.open(sys.stdin.buffer), sys.stdout.buffer, 1 << 20)" |
        tar -xf - -C "$dest"
else
    cat $(ls bundle.part.* | sort -t. -k3 -n) | tar -xf - -C "$dest"
fi
ls -l "$dest"
