"""Latency of the where-to-hang answer: ``omnihang_jax.where`` configs side by side.

    python -m experiments.bench_where --configs default,paper --batches 1,8,64 --out results/bench_where.json

Times ``load_where(config).answer`` (Stages 1-3 incl. CEM, one jitted call per batch; each pair
under its own key) on random clouds (the cost does not depend on the values) after one warm-up
call per shape (compilation, timed apart): median and p10/p90 over ``--repeat`` calls, the
configs interleaved so that each sees the same machine load. The observed-cloud check is host
code and is not part of these rows (``includes_check: false``).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time

import numpy as np

from experiments import _cli


def random_clouds(batch: int, points: int, seed: int):
    from omnihang_jax import stage3

    rng = np.random.default_rng(seed)

    def cloud(scale):
        x = rng.normal(scale=scale, size=(batch, points, 3)).astype(np.float32)
        n = rng.normal(size=(batch, points, 3)).astype(np.float32)
        return x, n / np.linalg.norm(n, axis=-1, keepdims=True)

    return stage3.PairClouds(*cloud(0.05), *cloud(0.1))


def bench(configs: dict, batches, repeat: int = 10, points: int = 4096) -> list[dict]:
    """Rows {config, batch, first_call_s, median_ms, p10_ms, p90_ms, pairs_per_s, ratio}."""
    from omnihang_jax import where

    loaded = {name: where.load_where(c) for name, c in configs.items()}
    rows = []
    for batch in batches:
        clouds = random_clouds(batch, points, batch)
        ids = np.arange(batch)
        first, times = {}, {n: [] for n in loaded}
        for name, w in loaded.items():
            t = time.perf_counter()
            w.answer(clouds, ids, 0)  # numpy out: the call has finished
            first[name] = time.perf_counter() - t
        for r in range(repeat):
            for name, w in loaded.items():
                t = time.perf_counter()
                w.answer(clouds, ids + r + 1, 0)
                times[name].append(time.perf_counter() - t)
        base = float(np.median(times[next(iter(loaded))]))
        for name in loaded:
            ms = np.asarray(times[name]) * 1000
            rows.append(dict(
                config=name, batch=batch, first_call_s=round(first[name], 2),
                median_ms=float(np.median(ms)), p10_ms=float(np.percentile(ms, 10)),
                p90_ms=float(np.percentile(ms, 90)),
                pairs_per_s=float(batch / np.median(ms) * 1000), repeat=repeat,
                ratio_to_first_config=float(np.median(ms) / 1000 / base), includes_check=False,
            ))  # fmt: skip
            print(json.dumps(rows[-1]), flush=True)
    return rows


def main(argv=None) -> dict:
    import jax

    from omnihang_jax import where

    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--configs", default="default,paper", help="names of where.CONFIGS")
    parser.add_argument("--batches", default="1,8", help="comma-separated batch sizes")
    parser.add_argument("--repeat", type=int, default=10)
    parser.add_argument("--points", type=int, default=4096, help="points per cloud")
    parser.add_argument("--out", default=None, help="write the rows here (JSON)")
    args = parser.parse_args(argv)
    names = [n for n in args.configs.split(",") if n]
    unknown = [n for n in names if n not in where.CONFIGS]
    if unknown or not names:
        raise ValueError(f"--configs {unknown or names}: known {sorted(where.CONFIGS)}")
    batches = [int(b) for b in args.batches.split(",")]
    if any(b < 1 for b in batches) or args.repeat < 1:
        raise ValueError("--batches and --repeat must be >= 1")
    rows = bench({n: where.CONFIGS[n] for n in names}, batches, args.repeat, args.points)
    result = dict(
        what="omnihang_jax.where answer (Stages 1-3, one jitted call per batch), no check",
        command="python -m experiments.bench_where " + " ".join(sys.argv[1:] if argv is None else argv),
        device=str(jax.devices()[0]), device_kind=jax.devices()[0].device_kind,
        versions=dict(jax=jax.__version__, python=platform.python_version()), rows=rows,
    )  # fmt: skip
    if args.out:
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)
    return result


if __name__ == "__main__":
    _cli.run(main)
