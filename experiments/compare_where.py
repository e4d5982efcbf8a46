"""Compare trained "where" weights on the pairs of the validation OBJECTS (never trained on by
runs with a validation split; see docs/networks.md), stage by stage, on the same batches.

    python -m experiments.compare_where --models weights/where_small_paper,runs/where/export \\
        --data datasets/paper --pairs 90 --out results/compare_where.json

Derives (if needed) --pairs random pairs of the fixed 10 % validation objects
(``data.validation_objects``) into DATA/derived/train, then evaluates each model's stage
losses / metrics (``train.make_eval_step``) on the same --batches batches of 16 with the same
noise keys. Caveat: models trained without the split (before the seventh session) may have
seen these objects.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os

import jax
import numpy as np

from experiments import _cli
from omnihang_jax import data, dataset_bridge, train


def validation_pairs(data_dir: str, fraction: float, n: int, seed: int) -> list[int]:
    with open(os.path.join(data_dir, "recipe.json")) as f:
        pairs = json.load(f)["pairs"]
    objects = sorted({p[0] for p in pairs if p[2] == "train"})
    val = data.validation_objects(objects, fraction)
    idx = [i for i, p in enumerate(pairs) if p[2] == "train" and p[0] in val]
    rng = np.random.default_rng(seed)
    return sorted(int(i) for i in rng.choice(idx, min(n, len(idx)), replace=False))


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--models", required=True, help="comma-separated weights folders")
    parser.add_argument("--data", default="datasets/paper", help="generated dataset")
    parser.add_argument("--stages", default="1", help="comma-separated stages (1,2a,2b)")
    parser.add_argument("--pairs", type=int, default=90, help="validation pairs to draw")
    parser.add_argument("--val-fraction", type=float, default=0.1)
    parser.add_argument("--batches", type=int, default=6)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=1, help="derive processes")
    parser.add_argument("--out", default=None, help="JSON")
    args = parser.parse_args(argv)
    picked = validation_pairs(args.data, args.val_fraction, args.pairs, args.seed)
    dataset_bridge.derive_dataset(
        args.data, splits=("train",), progress=False, workers=args.workers,
        pair_indices=set(picked),
    )  # fmt: skip
    derived = os.path.join(args.data, "derived", "train")
    files = [os.path.join(derived, f) for f in sorted(os.listdir(derived))
             if f.endswith(".npz") and int(f.split("_", 1)[0]) in set(picked)]  # fmt: skip
    if not files:
        raise FileNotFoundError(f"no derived validation pairs in {derived}")
    ds = data.NpzDirectoryDataset(files)
    result = {"pairs": len(files), "objects": len({data.object_name_of(f) for f in files}),
              "batches": args.batches, "batch_size": 16, "models": {}}  # fmt: skip
    for folder in args.models.split(","):
        result["models"][folder] = {}
        for stage in args.stages.split(","):
            config, params, step = train.restore_stage(os.path.join(folder, f"stage{stage}"))
            config = dataclasses.replace(
                config, train=dataclasses.replace(config.train, batch_size=16)
            )
            ev = jax.jit(train.make_eval_step(stage, config))
            rows = []
            for i in range(args.batches):
                batch = ds.sample_batch(np.random.default_rng([args.seed, 9, i]), 16)
                rows.append({k: float(v) for k, v in ev(params, batch, jax.random.key(i)).items()})
            metrics = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
            result["models"][folder][f"stage{stage}"] = {"step": int(step), **metrics}
            print(folder, stage, step, {k: round(v, 4) for k, v in metrics.items()}, flush=True)
    if args.out:
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)
    return result


if __name__ == "__main__":
    _cli.run(main)
