"""Derive the networks' per-pair training files from a generated dataset.

    python -m experiments.derive_dataset --data out/dataset_demo
    python -m experiments.train_where --data out/dataset_demo --preset tiny --out runs/demo

Reads DATA/recipe.json + DATA/shards/ and writes DATA/derived/<split>/<pair>.npz (HangSample
layout: partial clouds with normals, stable poses, soft contact maps, contact pairs) for
every pair with stable poses. Existing files are skipped: kill the job at any time and run
the same command again.
"""

from __future__ import annotations

import argparse
import gzip
import json
import os

from experiments import _cli
from omnihang_jax import dataset_bridge


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", required=True, help="generated dataset (recipe.json + shards/)")
    parser.add_argument("--out", default=None, help="output folder (default DATA/derived)")
    parser.add_argument(
        "--split", choices=["train", "test", "all"], default="all", help="split(s) to derive"
    )
    parser.add_argument("--limit", type=int, default=None, help="at most this many new files")
    parser.add_argument(
        "--workers", type=int, default=1, help="processes (0 = one per core); same files either way"
    )
    parser.add_argument(
        "--pairs-from",
        metavar="PAIRS_JSONL",
        default=None,
        help="derive only the pairs of an evaluation's per-pair JSONL (pair_index per line), "
        "e.g. results/hanging_success.pairs.jsonl",
    )
    parser.add_argument(
        "--clouds-only",
        action="store_true",
        help="clouds + stable poses without contact maps (~1.7x less CPU per pair), into "
        "DERIVED/<split>_clouds/: Stage 1, V and NCE inputs, not Stage 2's",
    )
    parser.add_argument(
        "--camera-scale",
        type=float,
        default=1.0,
        help="with --clouds-only: render at this fraction of the recipe's 640 x 480 (0.5: "
        "~3x less CPU per pair) into DERIVED/<split>_clouds_r<percent>/; training inputs only",
    )
    parser.add_argument(
        "--view",
        type=int,
        default=0,
        help="with --clouds-only: render each pair from its k-th other candidate view "
        "(1..n_views-1) into DERIVED/<split>_clouds[_r..]_v<k>/: more views for training",
    )
    parser.add_argument(
        "--per-object",
        type=int,
        default=None,
        metavar="N",
        help="derive at most N pairs of every object (seeded; the object-frame network's "
        "inputs: `--split train --clouds-only --camera-scale 0.5 --per-object 12`)",
    )
    parser.add_argument("--no-progress", action="store_true", help="disable progress bars")
    args = parser.parse_args(argv)
    pair_indices = None
    if args.pairs_from:
        opener = gzip.open if args.pairs_from.endswith(".gz") else open
        with opener(args.pairs_from, "rt") as f:  # an evaluation's records, gzipped or not
            pair_indices = {int(json.loads(line)["pair_index"]) for line in f if line.strip()}
    splits = ("train", "test") if args.split == "all" else (args.split,)
    if args.per_object is not None:
        if args.per_object < 1:
            parser.error(f"--per-object N needs N >= 1, got {args.per_object}")
        recipe = dataset_bridge.read_recipe(args.data)
        chosen = set()
        for split in splits:
            chosen |= dataset_bridge.pairs_per_object(recipe["pairs"], split, args.per_object)
        pair_indices = chosen if pair_indices is None else pair_indices & chosen
    summary = dataset_bridge.derive_dataset(
        args.data,
        args.out,
        splits=splits,
        limit=args.limit,
        progress=not args.no_progress,
        workers=args.workers or len(os.sched_getaffinity(0)),
        pair_indices=pair_indices,
        clouds_only=args.clouds_only,
        camera_scale=args.camera_scale,
        view=args.view,
    )
    print(json.dumps(summary, indent=1))
    return summary


if __name__ == "__main__":
    _cli.run(main)
