"""Pack a derived split into one padded array per field (the GPU trainers' fast input).

    python -m experiments.pack_dataset --data datasets/paper --split train --out /tmp/pack_train

Reads DATA/derived/<split>/*.npz (experiments.derive_dataset), writes OUT/<field>.npy
(memory-mappable; contact maps as uint8, normals float16: ~0.55 MB per paper-scale pair
instead of ~1.8 MB) and OUT/pack.json (files, object names, which pairs are valid, skipped
files with the reason). Pairs without a stable pose or with a broken file are skipped and
listed, not fatal. `experiments.train_where --data OUT` trains from it.
"""

from __future__ import annotations

import argparse
import glob
import json
import os

from experiments import _cli
from omnihang_jax import data


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", required=True, help="dataset folder (with derived/<split>/)")
    parser.add_argument(
        "--split",
        default="train",
        help="derived split(s) to pack, comma-separated (e.g. train_clouds_r50,train_clouds_r50_v1: "
        "two views of every pair in one pack)",
    )
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--threads", type=int, default=8, help="reader threads")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    splits = [x for x in args.split.split(",") if x]
    pattern = os.path.join(args.data, "derived", "{" + ",".join(splits) + "}", "*.npz")
    files = [
        f
        for sp in splits
        for f in sorted(glob.glob(os.path.join(args.data, "derived", sp, "*.npz")))
    ]
    files = files or sorted(glob.glob(os.path.join(args.data, "*.npz")))
    if not files:
        raise FileNotFoundError(f"no pair files at {pattern}: run experiments.derive_dataset first")
    meta = data.pack_dataset(files, args.out, threads=args.threads, progress=not args.no_progress)
    summary = {
        "out": args.out,
        "pairs": len(files),
        "packed": int(sum(meta["valid"])),
        "skipped": len(meta["skipped"]),
        "objects": len(set(meta["object_names"])),
    }
    print(json.dumps(summary, indent=1))
    return summary


if __name__ == "__main__":
    _cli.run(main)
