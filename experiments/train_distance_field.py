"""Train the object's neural unsigned distance field (``omnihang_jax.distance_field``).

    python -m experiments.train_distance_field --out weights/field_s49          # the device
    python -m experiments.train_distance_field --out runs/field_tiny --steps 200 --views 2 \\
        --objects 12 --batch 4 --queries 256                                   # a quick look

1. Renders, per training object, ``--views`` partial clouds and the whole visible surface
   (``--target-points``), exactly as ``experiments.train_completion`` (the same renderer and
   cache, ``DATA/derived/completion/``), and 4 views of every held-out (test split) object.
2. Splits the training objects by name into fit / validation (``data.validation_objects``,
   15 %, the hash of every trainer); held-out objects are never trained on.
3. Trains the field (L1 against the distance to the whole surface, a cosine schedule, the
   validation curve every ``--eval-every`` steps), writes ``OUT/`` (best-on-validation weights,
   ``history.jsonl``, ``curves.png``, a resumable checkpoint) and ``OUT/metrics.json``: L1 near
   the surface, over all queries and the 2 mm band's IoU on validation and held-out objects.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

from experiments.train_completion import DERIVED, VALIDATION_FRACTION, build_views
from omnihang_jax import dataset_bridge, distance_field
from omnihang_jax.data import validation_objects


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 1)[1])  # fmt: skip
    ap.add_argument("--data", default="datasets/paper", help="dataset folder (its recipe)")
    ap.add_argument("--out", default="weights/field", help="output folder")
    ap.add_argument("--views", type=int, default=12, help="partial views per training object")
    ap.add_argument("--points", type=int, default=2048, help="points kept per view")
    ap.add_argument("--target-points", type=int, default=16384, help="whole-surface points")
    ap.add_argument("--objects", type=int, default=None, help="at most this many training objects")
    ap.add_argument("--steps", type=int, default=20000)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--queries", type=int, default=2048, help="queries per cloud and step")
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--k", type=int, default=12, help="FieldConfig.k: neighbours per query")
    ap.add_argument(
        "--quantiles",
        default="0.5",
        help="FieldConfig.quantiles, comma-separated: the surface's (first) and upper ones",
    )
    ap.add_argument("--eval-every", type=int, default=1000)
    ap.add_argument("--workers", type=int, default=max(1, (os.cpu_count() or 2)))
    ap.add_argument("--no-cache", action="store_true", help="render again, write no cache")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    from sim.library import build_library

    config = dataset_bridge.dataset_config_from_recipe(dataset_bridge.read_recipe(args.data))
    library = build_library(config.library, progress=False)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    train_names = sorted(library.split["train"]["objects"])
    test_names = sorted(library.split["test"]["objects"])
    if args.objects:
        train_names, test_names = (
            train_names[: args.objects],
            test_names[: max(1, args.objects // 4)],
        )
    val_set = validation_objects(train_names, VALIDATION_FRACTION) or {train_names[-1]}
    fit_names = [n for n in train_names if n not in val_set]
    val_names = [n for n in train_names if n in val_set]
    tp = args.target_points
    tail = "" if tp == 2048 else f"_t{tp}"

    def cache(split, views, n):
        if args.no_cache:
            return None
        return Path(args.data, DERIVED, f"object_{split}_v{views}_n{n}{tail}.npz")

    all_train = build_views(args.data, "object", train_names, args.views, args.points,
                            args.workers, cache("train", args.views, len(train_names)),
                            target_points=tp)  # fmt: skip
    test = build_views(args.data, "object", test_names, 4, args.points, args.workers,
                       cache("test", 4, len(train_names)), target_points=tp)  # fmt: skip
    print(f"rendered {len(train_names)} + {len(test_names)} objects, {time.time() - t0:.0f} s",
          flush=True)  # fmt: skip
    idx = {n: i for i, n in enumerate(train_names)}
    fit = all_train.take([idx[n] for n in fit_names])
    val = all_train.take([idx[n] for n in val_names])
    quantiles = tuple(float(x) for x in args.quantiles.split(",") if x)
    cfg = distance_field.FieldConfig(k=args.k, quantiles=quantiles)
    tc = distance_field.FieldTrainConfig(steps=args.steps, batch=args.batch, queries=args.queries,
                                         lr=args.lr, eval_every=min(args.eval_every, args.steps))  # fmt: skip
    summary = distance_field.train_field(cfg, fit, val, out, tc, progress=not args.no_progress)
    cfg, params, meta = distance_field.load_field(out)
    held = distance_field.evaluate(params, test, cfg)
    metrics = dict(
        fit_objects=len(fit_names), validation_objects=len(val_names), test_objects=len(test_names),
        views=args.views, target_points=tp, steps=args.steps, best_step=summary["best_step"],
        validation=meta["val"], held_out=held, seconds=round(time.time() - t0, 1),
    )  # fmt: skip
    print(f"validation {meta['val']}\nheld-out {held}", flush=True)
    from sim import atomic

    atomic.write_text(out / "metrics.json", json.dumps(metrics, indent=2))
    return metrics


if __name__ == "__main__":
    from experiments import _cli

    _cli.run(main)
