"""Compare the labels of two generations of the same shards (e.g. GPU vs CPU backend).

    python -m experiments.compare_shards --a datasets/paper --b /tmp/gmjx \
        --out results/dataset_gpu_vs_cpu.json

For every shard present in both ``A/shards`` and ``B/shards`` (same recipe, so the same
pairs and seeds), counts per side: pairs with stable poses, kept stable poses, raw stable
settles, candidates, take-off rejections; and how many pairs agree on "has a stable pose",
plus the agreement of the collision labels where both sides labelled the same poses.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np

from experiments import _cli

COUNTS = ("n_candidates", "n_stable_raw", "n_takeoff_rejected", "n_fallen", "n_penetrating")


def compare_shard(a: dict, b: dict) -> dict:
    """Counts of one shard's labels on both sides (``a``, ``b``: the npz contents)."""
    if not np.array_equal(a["pair_index"], b["pair_index"]):
        raise ValueError("the shards hold different pairs (another recipe?)")
    na, nb = np.diff(a["stable_offsets"]), np.diff(b["stable_offsets"])
    row = {
        "pairs": int(len(na)),
        "with_stable_a": int((na > 0).sum()),
        "with_stable_b": int((nb > 0).sum()),
        "with_stable_agree": int(((na > 0) == (nb > 0)).sum()),
        "stable_poses_a": int(na.sum()),
        "stable_poses_b": int(nb.sum()),
        "pairs_same_stable_count": int((na == nb).sum()),
    }
    for key in COUNTS:
        row[f"{key}_a"], row[f"{key}_b"] = int(a[key].sum()), int(b[key].sum())
    same = a["collision_label"].shape == b["collision_label"].shape
    row["collision_labels_compared"] = int(a["collision_label"].size) if same else 0
    row["collision_labels_equal"] = (
        int((a["collision_label"] == b["collision_label"]).sum()) if same else 0
    )
    return row


def compare(dir_a: str | os.PathLike, dir_b: str | os.PathLike) -> dict:
    names_a = {p.name for p in Path(dir_a, "shards").glob("shard_*.npz")}
    names_b = {p.name for p in Path(dir_b, "shards").glob("shard_*.npz")}
    common = sorted(names_a & names_b)
    if not common:
        raise SystemExit(f"no shard in both {dir_a}/shards and {dir_b}/shards")
    shards = {}
    for name in common:
        with np.load(Path(dir_a, "shards", name)) as a, np.load(Path(dir_b, "shards", name)) as b:
            shards[name] = compare_shard(dict(a), dict(b))
    total = {k: sum(r[k] for r in shards.values()) for k in next(iter(shards.values()))}
    return {
        "a": os.fspath(dir_a),
        "b": os.fspath(dir_b),
        "shards": len(common),
        "total": total,
        "per_shard": shards,
    }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--a", required=True, help="dataset folder A (e.g. the CPU one)")
    parser.add_argument("--b", required=True, help="dataset folder B (e.g. the GPU one)")
    parser.add_argument("--out", default=None, help="write the comparison here (JSON)")
    args = parser.parse_args(argv)
    result = compare(args.a, args.b)
    print(json.dumps(result["total"], indent=1))
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    _cli.run(main)
