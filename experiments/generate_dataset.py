"""Generate (or resume) the hanging dataset.

    python -m experiments.generate_dataset --preset demo --out out/dataset_demo
    python -m experiments.generate_dataset --preset paper --out data/paper --backend mjx

Shards already on disk are never redone; kill the job at any time and run the same command
again. The dataset card is written at the end (DIR/dataset_card.json and .md).
"""

from __future__ import annotations

import argparse
import dataclasses
import json

from sim import dataset


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--preset", choices=sorted(dataset.PRESETS), default="demo", help="dataset size preset"
    )
    parser.add_argument("--out", required=True, help="output directory (resumed if it exists)")
    parser.add_argument("--backend", choices=["cpu", "mjx"], default="cpu", help="physics backend")
    parser.add_argument(
        "--max-pairs-per-category", type=int, default=None, help="override: objects per category"
    )
    parser.add_argument(
        "--max-pairs",
        type=int,
        default=None,
        help="a seeded random subset of N pairs (to measure rates)",
    )
    parser.add_argument("--seed", type=int, default=None, help="override the dataset seed")
    parser.add_argument("--no-progress", action="store_true", help="disable progress bars")
    args = parser.parse_args(argv)
    config = dataset.PRESETS[args.preset]
    if args.max_pairs_per_category is not None:
        config = dataclasses.replace(config, max_objects_per_category=args.max_pairs_per_category)
    if args.max_pairs is not None:
        config = dataclasses.replace(config, max_pairs=args.max_pairs)
    if args.seed is not None:
        config = dataclasses.replace(config, seed=args.seed)
    card = dataset.generate(
        config, args.out, preset=args.preset, backend=args.backend, progress=not args.no_progress
    )
    summary = {
        k: card[k]
        for k in (
            "pairs_done",
            "pairs_with_stable_poses",
            "train_pairs",
            "test_pairs",
            "stable_yield",
        )
    }
    print(json.dumps(summary, indent=1))
    print(
        f"pairs/min this run: {card['timings']['pairs_per_min_this_run']:.1f}; card: {args.out}/dataset_card.md"
    )
    return card


if __name__ == "__main__":
    main()
