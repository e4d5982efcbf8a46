"""Inference latency of the where-to-hang pipeline (Stage 1 proposals + Stage 2 updates).

    python -m experiments.bench_where --model weights/where_small_paper --out results/bench_where.json
    python -m experiments.bench_where --preset small --out /tmp/bench_where.json  # random weights

Times the jitted ``predict`` (clouds -> K pose proposals with Stage-2 translations) at each
batch size after one warm-up call (compilation, timed apart), as the median and the 10th/90th
percentiles over ``--repeat`` calls, each ended by ``block_until_ready``. Weights do not
change the cost, so random weights of a preset measure the same thing when no trained model
is at hand (``weights`` in the JSON says which). Writes device, versions and the settings.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import jax
import numpy as np

from experiments import _cli
from omnihang_jax import train
from omnihang_jax.predict import Predictor, load_predictor


def _random_predictor(preset: str, seed: int) -> Predictor:
    config = train.PRESETS[preset]
    key1, key2 = jax.random.split(jax.random.key(seed))
    params1 = train.make_init_state("1", config)(key1).params
    params2 = train.make_init_state("2b", config)(key2).params
    return Predictor(config.stage1, params1, config.stage2, params2, seed=seed)


def measure(predictor: Predictor, batch: int, points: int, proposals: int, repeat: int) -> dict:
    rng = np.random.default_rng(batch)
    obj = rng.normal(scale=0.05, size=(batch, points, 3)).astype(np.float32)
    sup = rng.normal(scale=0.1, size=(batch, points, 3)).astype(np.float32)
    t = time.perf_counter()
    jax.block_until_ready(predictor(obj, sup, num_proposals=proposals))
    first = time.perf_counter() - t
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        out = predictor(obj, sup, num_proposals=proposals)
        jax.block_until_ready(out)
        times.append(time.perf_counter() - t)
    times = np.asarray(times) * 1000
    return {
        "batch": batch,
        "proposals": proposals,
        "first_call_s": first,
        "median_ms": float(np.median(times)),
        "p10_ms": float(np.percentile(times, 10)),
        "p90_ms": float(np.percentile(times, 90)),
        "pairs_per_s": float(batch / np.median(times) * 1000),
        "repeat": repeat,
    }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--model", default=None, help="folder written by train_where")
    parser.add_argument(
        "--preset", choices=sorted(train.PRESETS), default="small", help="without --model"
    )
    parser.add_argument("--batches", default="1,256", help="comma-separated batch sizes")
    parser.add_argument("--proposals", type=int, default=None, help="K (default: the model's)")
    parser.add_argument("--repeat", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--compare",
        default=None,
        metavar="MODEL",
        help="a second model timed beside --model at each batch size (same clouds, same "
        "points: the larger of the two networks' design sizes); writes the ratio of medians",
    )
    parser.add_argument(
        "--points", type=int, default=None, help="points per cloud (default: the model's)"
    )
    parser.add_argument("--out", required=True, help="output JSON")
    args = parser.parse_args(argv)
    if args.model:
        predictor, weights = load_predictor(args.model, seed=args.seed), args.model
    else:
        predictor, weights = _random_predictor(args.preset, args.seed), f"random {args.preset}"
    other = load_predictor(args.compare, seed=args.seed) if args.compare else None
    points = args.points or max(predictor.num_points, other.num_points if other else 0)
    k = args.proposals or predictor.stage1_config.num_eval_samples
    rows, compared = [], []
    for b in (int(x) for x in args.batches.split(",")):
        rows.append(measure(predictor, b, points, k, args.repeat))
        print(json.dumps(rows[-1]), flush=True)
        if other is not None:  # side by side, in the same run: the ratio is what to read
            compared.append(measure(other, b, points, k, args.repeat))
            compared[-1]["ratio_to_model"] = compared[-1]["median_ms"] / rows[-1]["median_ms"]
            print(json.dumps(compared[-1]), flush=True)
    result = {
        "latency": rows,
        "weights": weights,
        **({"compare": {"weights": args.compare, "latency": compared}} if other else {}),
        "points_per_cloud": points,
        "device": str(jax.devices()[0].device_kind),
        "jax_backend": jax.default_backend(),
        "versions": {"jax": jax.__version__, "python": platform.python_version()},
    }
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(result, f, indent=1)
    return result


if __name__ == "__main__":
    _cli.run(main)
