#!/usr/bin/env bash
# Pack the wheels the GPU benchmark needs into parts that each fit one device call.
#
#   scripts/split_wheels.sh [PART_MIB]        (run here, in the repo root; default 56)
#   SLIM=0 scripts/split_wheels.sh            keep warp-clang.so (one part more)
#   XZ=1 scripts/split_wheels.sh 60           xz stream: 2 parts of <= 60 MiB (~3 min here)
#   NO_PYBULLET=1 XZ=1 scripts/split_wheels.sh 30   dataset generation only (no PyBullet baseline)
#   RECUT=1 scripts/split_wheels.sh 23        re-cut the existing stream into smaller parts
#
# The device machine has no mujoco, mujoco-mjx, trimesh, pybullet or warp-lang, and one
# call carries at most 64 MiB (working tree + carried paths). warp-lang 1.19.0's wheel
# alone is 149 MB, so the set is packed into one tar stream and cut into PART_MIB pieces:
#
#   .whl/      the small set (mujoco, mujoco-core, mujoco-studio, glfw, mujoco-mjx,
#              trimesh, manifold3d, websockets, pybullet-3.2.7-src.tar.gz); must exist
#   .whl_gpu/  warp-lang 1.19.0 (downloaded here if missing), slimmed to .whl_gpu/slim/:
#              warp/bin/warp-clang.so (Warp's CPU-device LLVM; optional, Warp loads it
#              only if present), warp/examples and warp/tests removed, RECORD rewritten
#   .whlparts/pK/   part K (bundle.part.K) + MANIFEST (sha256 of every part and of the
#              whole stream) in every part folder. Carry .whlparts/pK in call K.
#
# Both .whl_gpu and .whlparts are added to .git/info/exclude (they must be ignored paths
# to be carried). See scripts/device_bench.md for the calls.
set -euo pipefail
PART_MIB=${1:-56}
cd "$(git rev-parse --show-toplevel)"
for d in /.whl/ /.whl_gpu/ /.whlparts/; do
    grep -qxF "$d" .git/info/exclude || echo "$d" >>.git/info/exclude
done
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] && PY=.venv/bin/python
ls .whl/mujoco_mjx-3.17.0-py3-none-any.whl .whl/mujoco_core-4.0.0-*.whl >/dev/null

WARP=warp_lang-1.19.0-py3-none-manylinux_2_28_x86_64.whl
if [ ! -f ".whl_gpu/$WARP" ]; then
    "$PY" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 \
        --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 \
        -d .whl_gpu warp-lang==1.19.0
fi
mkdir -p .whl_gpu/slim
"$PY" - ".whl_gpu/$WARP" ".whl_gpu/slim/$WARP" <<'EOF'
import os, sys, zipfile

src, dst = sys.argv[1:3]
drop = ("warp/examples/", "warp/tests/")
if os.environ.get("SLIM", "1") != "0":  # SLIM=0 keeps Warp's CPU compiler (4 parts)
    drop += ("warp/bin/warp-clang.so",)
with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as zout:
    for info in zin.infolist():
        name = info.filename
        if name.startswith(drop):
            continue
        data = zin.read(info)
        if name.endswith(".dist-info/RECORD"):
            lines = data.decode().splitlines(keepends=True)
            data = "".join(line for line in lines if not line.startswith(drop)).encode()
        # XZ=1: store uncompressed, the xz stream around the tar compresses it (81 vs 115 MB)
        kind = zipfile.ZIP_STORED if os.environ.get("XZ") == "1" else zipfile.ZIP_DEFLATED
        zout.writestr(info, data, compress_type=kind, compresslevel=None if os.environ.get("XZ") == "1" else 9)
print(f"slim warp-lang wheel: {dst}")
EOF

if [ "${RECUT:-0}" = 1 ]; then
    # RECUT=1: cut the existing stream (.whlparts/p*/bundle.part.*) into PART_MIB pieces
    # without rebuilding or recompressing it (seconds instead of minutes)
    CODEC=$(awk '$1 == "codec" {print $2}' .whlparts/MANIFEST)
    mkdir -p .whlparts.new/tmp
    cat $(ls .whlparts/p*/bundle.part.* | awk -F. '{print $NF, $0}' | sort -n | cut -d' ' -f2) |
        split -b "${PART_MIB}M" -d -a 1 - .whlparts.new/tmp/bundle.part.
    rm -rf .whlparts && mv .whlparts.new .whlparts
else
rm -rf .whlparts && mkdir -p .whlparts/tmp
# the stream: .whl/* and the slim warp wheel, flat, in one tar (wheels are already zips)
CODEC=tar
COMPRESS=cat
if [ "${XZ:-0}" = 1 ]; then CODEC=tar.xz COMPRESS="xz -6 -T0"; fi
# NO_PYBULLET=1 leaves out the PyBullet sdist (only the benchmark's baseline needs it; 6 MB)
EXCL=()
[ "${NO_PYBULLET:-0}" = 1 ] && EXCL=(--exclude='./pybullet-*')
tar -cf - "${EXCL[@]}" -C .whl . -C ../.whl_gpu/slim "$WARP" | $COMPRESS | split -b "${PART_MIB}M" -d -a 1 - .whlparts/tmp/bundle.part.
fi
n=$(ls .whlparts/tmp | wc -l)
(
    cd .whlparts/tmp
    echo "parts $n"
    echo "codec $CODEC"
    sha256sum bundle.part.*
    echo "whole $(cat bundle.part.* | sha256sum | cut -d' ' -f1)"
) >.whlparts/MANIFEST
for k in $(seq 0 $((n - 1))); do
    mkdir -p ".whlparts/p$((k + 1))"
    mv ".whlparts/tmp/bundle.part.$k" ".whlparts/p$((k + 1))/"
    cp .whlparts/MANIFEST ".whlparts/p$((k + 1))/MANIFEST"
done
rmdir .whlparts/tmp
du -b .whlparts/p* | sort -k2
echo "$n parts: carry .whlparts/p1 .. .whlparts/p$n in consecutive calls (scripts/device_bench.md)"
