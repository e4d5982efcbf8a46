#!/usr/bin/env bash
# Makes the working tree small enough to travel to the device machine (64 MiB with the carried
# wheels): `out MODE` moves the tracked files that the device's MODE does not read to
# /tmp/omnihang_lean (results/, docs/img/, datasets/external/ and the other figure's weights), `back`
# moves them back. Run `back` before anything stages or commits: while they are out, git sees
# them as deleted.
#
#   bash scripts/device_lean.sh out where   # scripts/device_evaluate.sh MODE=where / bench
#   bash scripts/device_lean.sh out paths   # MODE=paths
#   bash scripts/device_lean.sh size        # what travels now (tracked + untracked, not ignored)
#   bash scripts/device_lean.sh back
set -euo pipefail
cd "$(git rev-parse --show-toplevel)"
LEAN=${LEAN:-/tmp/omnihang_lean}
LIST=$LEAN/moved.txt

size() {  # bytes of the tree that travels, plus the wheel folders given
    local tree wheels=0
    tree=$({ git ls-files -z; git ls-files -z --others --exclude-standard; } |
        xargs -0 du -cb 2>/dev/null | awk '$2 == "total" {s += $1} END {print s + 0}' || true)
    for w in "$@"; do wheels=$((wheels + $(du -sb "$w" | cut -f1))); done
    echo "tree $tree B + wheels $wheels B = $((tree + wheels)) B of 67108864 (64 MiB)"
}

case ${1:-} in
    out)
        [ ! -s "$LIST" ] || { echo "already out ($LIST): run back first" >&2; exit 1; }
        case ${2:-} in
            where | bench) other="weights/nce weights/approach weights/approach_routes" ;;
            paths) other="weights/stage12 weights/stage1_frames weights/canon weights/value weights/rankers" ;;
            *) echo "usage: $0 out where|paths" >&2; exit 2 ;;
        esac
        mkdir -p "$LEAN"
        # shellcheck disable=SC2086
        git ls-files -z -- results docs/img datasets/external $other | while IFS= read -r -d '' f; do
            [ -e "$f" ] || continue
            mkdir -p "$LEAN/$(dirname "$f")"
            mv "$f" "$LEAN/$f"
            printf '%s\n' "$f" >>"$LIST"
        done
        echo "moved $(wc -l <"$LIST") files to $LEAN"
        case $2 in
            paths) size .whl_min .whl_train .whl_plan ;;
            *) size .whl_min .whl_train ;;
        esac
        ;;
    back)
        [ -s "$LIST" ] || { echo "nothing out ($LIST)" >&2; exit 0; }
        while IFS= read -r f; do
            if [ -e "$f" ]; then
                echo "kept the tree's $f (the moved copy stays in $LEAN)" >&2
                continue
            fi
            mkdir -p "$(dirname "$f")"
            mv "$LEAN/$f" "$f"
        done <"$LIST"
        rm "$LIST"
        echo "moved back; git status shows no deletions from this script"
        ;;
    size) size "${@:2}" ;;
    *) echo "usage: $0 out where|paths | back | size [WHEEL_DIR...]" >&2; exit 2 ;;
esac
